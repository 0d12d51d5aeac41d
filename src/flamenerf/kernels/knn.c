/* The k nearest mesh vertices of many points, for CPUs: meshes.nearest_vertices' answer
 * without a k-d tree.
 *
 * A face mesh has a few hundred vertices and the points that ask lie near it (a ray's
 * samples around the face), so a tree prunes little: SciPy's cKDTree took ~0.75 us per
 * point (k = 4, 807 vertices). Here each point walks its own mesh's vertices eight at a
 * time (AVX-512, double precision; a plain loop elsewhere, see knn_vectorised) and keeps
 * its k best in a sorted list, touched only by a vertex that beats the k-th best so far
 * (or lies within `bound` while fewer than k are found). The previous
 * point's neighbours (consecutive points are one ray's samples, close together) bound
 * that k-th distance from the start, so few vertices are ever inserted: a 128 px viewer
 * update's queries 41 -> 13 ms on a Zen 4 core, the same answer as the tree.
 *
 * Layouts: pts (P, 3) float32; which (P,) int64 (each point's mesh) or NULL (all on
 * mesh 0); verts (M, V, 3) float32; out d2 (P, k) float32 (squared distance, +inf where
 * fewer than k vertices lie within `bound`) and idx (P, k) int64 into the M·V stacked
 * vertices (0 where none). A vertex counts when its distance is at most `bound`; vertices
 * at exactly equal distances keep the order in which they were met. Returns 0, or 1 for a
 * k outside 1..KNN_MAX_K, 2 when memory ran out.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#define KNN_MAX_K 16

/* insert distance d of vertex v into the sorted lists (d2 ascending) of length k */
static inline void keep(double *best, int64_t *bi, int k, double d, int64_t v) {
    int j = k - 1;
    while (j > 0 && best[j - 1] > d) {
        best[j] = best[j - 1];
        bi[j] = bi[j - 1];
        j--;
    }
    best[j] = d;
    bi[j] = v;
}

#if defined(__AVX512F__)
#include <immintrin.h>
#endif

/* 1 where the walk runs eight vertices at a time; the plain loop (a build without AVX-512)
 * took 65 ms for the 41 ms the k-d tree needs on a viewer update's queries, so callers keep
 * the tree there */
int knn_vectorised(void) {
#if defined(__AVX512F__)
    return 1;
#else
    return 0;
#endif
}

int knn_forward(const float *pts, int64_t P, const int64_t *which, const float *verts,
                int64_t M, int64_t V, int32_t k, double bound, float *out_d2,
                int64_t *out_idx, int32_t threads) {
    if (k < 1 || k > KNN_MAX_K) return 1;
    /* the vertices as double-precision columns, each mesh's padded to a multiple of 8 with
     * far-away points that never win */
    const int64_t Vp = (V + 7) / 8 * 8;
    double *cols = (double *)aligned_alloc(64, sizeof(double) * 3 * M * Vp + 64);
    if (!cols) return 2;
    for (int64_t m = 0; m < M; m++)
        for (int64_t v = 0; v < Vp; v++)
            for (int a = 0; a < 3; a++)
                cols[(m * 3 + a) * Vp + v] = v < V ? (double)verts[(m * V + v) * 3 + a]
                                                   : INFINITY;
    const double b2 = bound * bound;
#pragma omp parallel num_threads(threads)
    {
    /* the previous point's neighbours (the same thread's, on the same mesh): consecutive
     * points are a ray's samples, close together, so those vertices bound the new point's
     * k-th distance from the start and the walk below keeps only the few that beat it */
    int64_t seed[KNN_MAX_K], seed_mesh = -1;
#pragma omp for schedule(static, 256)
    for (int64_t i = 0; i < P; i++) {
        const int64_t m = which ? which[i] : 0;
        const double *cx = cols + (m * 3 + 0) * Vp, *cy = cols + (m * 3 + 1) * Vp,
                     *cz = cols + (m * 3 + 2) * Vp;
        const double px = pts[3 * i], py = pts[3 * i + 1], pz = pts[3 * i + 2];
        double best[KNN_MAX_K];
        int64_t bi[KNN_MAX_K] = {0};
        for (int j = 0; j < k; j++) { best[j] = INFINITY; bi[j] = -1; }
        /* the k-th best so far, or the bound while fewer than k are found: every vertex
         * at most this far is a candidate */
        double worst = b2;
        if (seed_mesh == m) {
            double far = 0.0;
            for (int j = 0; j < k; j++) {
                const double dx = px - cx[seed[j]], dy = py - cy[seed[j]],
                             dz = pz - cz[seed[j]];
                const double d = dx * dx + dy * dy + dz * dz;
                far = d > far ? d : far;
            }
            /* a bound, not a distance: made a little larger so that rounding (this sum
             * may be fused where the walk's is not) never drops the seeds themselves */
            far *= 1.0 + 1e-9;
            worst = far < worst ? far : worst;
        }
#if defined(__AVX512F__)
        const __m512d X = _mm512_set1_pd(px), Y = _mm512_set1_pd(py), Z = _mm512_set1_pd(pz);
        for (int64_t v = 0; v < Vp; v += 8) {
            const __m512d dx = _mm512_sub_pd(X, _mm512_load_pd(cx + v));
            const __m512d dy = _mm512_sub_pd(Y, _mm512_load_pd(cy + v));
            const __m512d dz = _mm512_sub_pd(Z, _mm512_load_pd(cz + v));
            const __m512d d = _mm512_add_pd(_mm512_add_pd(_mm512_mul_pd(dx, dx),
                                                          _mm512_mul_pd(dy, dy)),
                                            _mm512_mul_pd(dz, dz));
            __mmask8 hit = _mm512_cmp_pd_mask(d, _mm512_set1_pd(worst), _CMP_LE_OQ);
            if (!hit) continue;
            double ds[8];
            _mm512_storeu_pd(ds, d);
            while (hit) {
                const int l = __builtin_ctz(hit);
                hit &= hit - 1;
                if (v + l < V && ds[l] <= worst && (bi[k - 1] < 0 || ds[l] < best[k - 1])) {
                    keep(best, bi, k, ds[l], v + l);
                    if (bi[k - 1] >= 0) worst = best[k - 1];
                }
            }
        }
#else
        for (int64_t v = 0; v < V; v++) {
            const double dx = px - cx[v], dy = py - cy[v], dz = pz - cz[v];
            const double d = dx * dx + dy * dy + dz * dz;
            if (d <= worst && (bi[k - 1] < 0 || d < best[k - 1])) {
                keep(best, bi, k, d, v);
                if (bi[k - 1] >= 0) worst = best[k - 1];
            }
        }
#endif
        seed_mesh = bi[k - 1] >= 0 ? m : -1;
        for (int j = 0; j < k; j++) seed[j] = bi[j];
        for (int j = 0; j < k; j++) {
            if (bi[j] >= 0) {
                /* the tree reports sqrt(d²); its caller squares it again */
                const double r = sqrt(best[j]);
                out_d2[i * k + j] = (float)(r * r);
                out_idx[i * k + j] = m * V + bi[j];
            } else {
                out_d2[i * k + j] = INFINITY;
                out_idx[i * k + j] = 0;
            }
        }
    }
    }
    free(cols);
    return 0;
}
