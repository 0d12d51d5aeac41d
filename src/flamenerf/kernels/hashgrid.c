/* Multiresolution hash-grid encoding, forward and backward, for CPUs.
 *
 * The same maths as flamenerf.model.encodings.HashGrid's PyTorch path (which stays the
 * reference and the GPU path): trilinear interpolation of per-level feature tables,
 * corners c = ix*4 + iy*2 + iz, dense levels indexed x + y(r+1) + z(r+1)^2, hashed levels
 * (x*1) ^ (y*2654435761) ^ (z*805459861) masked to the table size.
 *
 * Written by hand because on a CPU the PyTorch composition of ~40 elementwise ops per
 * level is bound by memory traffic; one pass per point does the same work several times
 * faster. Loops are level-major (one level's table at a time stays in cache: the same
 * layout that made the PyTorch path fast). Deterministic, so that a resumed run repeats
 * an uninterrupted one: the forward pass is parallel over points, the backward pass over
 * levels, and every sum runs in a fixed order.
 *
 * Layouts: x (N, 3) float32 in [0, 1] (clamped here, as the reference does); table l is
 * (T_l, F) float32, an entry's features side by side, so that the two x-neighbours of a
 * corner (indices that differ in the low bits) usually share one cache line; out and gout
 * are (N, L*F) with level-major features; the forward pass writes rows `out_stride` floats
 * apart (L*F, or a wider buffer's row: the features land beside others without a copy).
 */
#include <math.h>
#include <stdint.h>

#define P1 2654435761LL
#define P2 805459861LL

static inline void cell(const float *xp, int64_t r, int64_t base[3], float frac[3],
                        int inside[3]) {
    for (int k = 0; k < 3; k++) {
        float v = xp[k];
        inside[k] = (v >= 0.0f && v <= 1.0f);
        v = v < 0.0f ? 0.0f : (v > 1.0f ? 1.0f : v);
        float pos = v * (float)r;
        float b = (float)(int64_t)pos; /* floor: pos >= 0 (and no libm call) */
        if (b > (float)(r - 1)) b = (float)(r - 1);
        base[k] = (int64_t)b;
        frac[k] = pos - b;
    }
}

static inline void corners(const int64_t b[3], int64_t r, int dense, int64_t mask,
                           int64_t idx[8]) {
    int64_t tx[2], ty[2], tz[2];
    if (dense) {
        int64_t s1 = r + 1, s2 = (r + 1) * (r + 1);
        tx[0] = b[0]; tx[1] = b[0] + 1;
        ty[0] = b[1] * s1; ty[1] = (b[1] + 1) * s1;
        tz[0] = b[2] * s2; tz[1] = (b[2] + 1) * s2;
        for (int c = 0; c < 8; c++) idx[c] = tx[c >> 2] + ty[(c >> 1) & 1] + tz[c & 1];
    } else {
        tx[0] = b[0]; tx[1] = b[0] + 1;
        ty[0] = b[1] * P1; ty[1] = (b[1] + 1) * P1;
        tz[0] = b[2] * P2; tz[1] = (b[2] + 1) * P2;
        for (int c = 0; c < 8; c++)
            idx[c] = (tx[c >> 2] ^ ty[(c >> 1) & 1] ^ tz[c & 1]) & mask;
    }
}

/* Point xp on level (r, dense): its cell's 8 corner indices, its position inside the cell,
 * and which of its coordinates lie inside [0, 1]. */
static inline void locate(const float *xp, int64_t r, int dense, int64_t mask, int64_t idx[8],
                          float fr[3], int inside[3]) {
    int64_t b[3];
    cell(xp, r, b, fr, inside);
    corners(b, r, dense, mask, idx);
}

static inline void weights(const float f[3], float w[8]) {
    float wx[2] = {1.0f - f[0], f[0]}, wy[2] = {1.0f - f[1], f[1]},
          wz[2] = {1.0f - f[2], f[2]};
    for (int c = 0; c < 8; c++) w[c] = wx[c >> 2] * wy[(c >> 1) & 1] * wz[c & 1];
}

/* One level with F <= 16 features (every grid of the presets, and the bakes) for 16 points
 * at a time with AVX-512 (32-bit lanes; the table read by gathers for F = 1, by 64-bit
 * gathers for F = 2, by one vector load per point and corner for F >= 3): 3x faster than
 * the generic loop for `fast`'s grid on an Intel Xeon. 32-bit index arithmetic gives the
 * 64-bit path's indices while the table holds < 2^31 floats (the hash is masked from the
 * same low bits; a dense index is < (r+1)^3 <= the table's size). The same operations in
 * the same order as `locate`, `weights` and the generic loop; only the rounding of a fused
 * multiply-add may differ. Built only where the compiler targets AVX-512 (-march=native on such a CPU);
 * elsewhere the generic loop runs. */
#if defined(__AVX512F__)
#include <immintrin.h>
#define HAVE_LEVEL_SIMD 1
#define SIMD_MAX_F 16

/* 16 points (lanes) of one level: their cells, as `cell` and `corners` compute them */
typedef struct {
    __m512i tx[2], ty[2], tz[2]; /* the corner index's terms along x, y, z (low, high) */
    __m512 w[3][2];              /* the trilinear weights along x, y, z (low, high) */
    __mmask16 inside[3];         /* lanes whose coordinate lies inside [0, 1] */
} cells16;

/* the x, y or z coordinates of 16 points from their 48 interleaved floats v0 | v1 | v2:
 * one two-register permutation takes what lies in v0 | v1, a second the rest from v2
 * (three strided gathers per level cost more than six permutations on a Zen 4) */
static inline __attribute__((always_inline)) __m512
axis16(__m512 v0, __m512 v1, __m512 v2, int a) {
    static const int32_t first[3][16] = {
        {0, 3, 6, 9, 12, 15, 18, 21, 24, 27, 30, 0, 0, 0, 0, 0},
        {1, 4, 7, 10, 13, 16, 19, 22, 25, 28, 31, 0, 0, 0, 0, 0},
        {2, 5, 8, 11, 14, 17, 20, 23, 26, 29, 0, 0, 0, 0, 0, 0}};
    static const int32_t second[3][16] = {
        {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 17, 20, 23, 26, 29},
        {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 18, 21, 24, 27, 30},
        {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 16, 19, 22, 25, 28, 31}};
    const __m512 t = _mm512_permutex2var_ps(v0, _mm512_loadu_si512(first[a]), v1);
    return _mm512_permutex2var_ps(t, _mm512_loadu_si512(second[a]), v2);
}

static inline __attribute__((always_inline)) __mmask16 floats16(int64_t left) {
    return left >= 16 ? (__mmask16)0xFFFF
                      : left <= 0 ? (__mmask16)0 : (__mmask16)((1u << left) - 1u);
}

static inline __attribute__((always_inline)) cells16
locate16(const float *xp, int64_t m, int64_t r, int dense) {
    const __m512 rf = _mm512_set1_ps((float)r), top = _mm512_set1_ps((float)(r - 1));
    const __m512 zero = _mm512_setzero_ps(), one = _mm512_set1_ps(1.0f);
    const __m512i ione = _mm512_set1_epi32(1);
    const __m512i sy = dense ? _mm512_set1_epi32((int32_t)(uint32_t)(r + 1))
                             : _mm512_set1_epi32((int32_t)(uint32_t)P1);
    const __m512i sz = dense ? _mm512_set1_epi32((int32_t)(uint32_t)((r + 1) * (r + 1)))
                             : _mm512_set1_epi32((int32_t)(uint32_t)P2);
    /* the m (<= 16) points' 3m floats; lanes past them read 0 */
    const __m512 v0 = _mm512_maskz_loadu_ps(floats16(3 * m), xp);
    const __m512 v1 = _mm512_maskz_loadu_ps(floats16(3 * m - 16), xp + 16);
    const __m512 v2 = _mm512_maskz_loadu_ps(floats16(3 * m - 32), xp + 32);
    cells16 c;
    __m512i b[3];
    for (int a = 0; a < 3; a++) {
        __m512 v = axis16(v0, v1, v2, a);
        c.inside[a] = _mm512_cmp_ps_mask(v, zero, _CMP_GE_OQ)
                      & _mm512_cmp_ps_mask(v, one, _CMP_LE_OQ);
        v = _mm512_min_ps(_mm512_max_ps(v, zero), one);
        __m512 pos = _mm512_mul_ps(v, rf);
        __m512 bb = _mm512_cvtepi32_ps(_mm512_cvttps_epi32(pos));
        bb = _mm512_min_ps(bb, top);
        b[a] = _mm512_cvttps_epi32(bb);
        const __m512 f = _mm512_sub_ps(pos, bb);
        c.w[a][0] = _mm512_sub_ps(one, f);
        c.w[a][1] = f;
    }
    c.tx[0] = b[0]; c.tx[1] = _mm512_add_epi32(b[0], ione);
    c.ty[0] = _mm512_mullo_epi32(b[1], sy);
    c.ty[1] = _mm512_mullo_epi32(_mm512_add_epi32(b[1], ione), sy);
    c.tz[0] = _mm512_mullo_epi32(b[2], sz);
    c.tz[1] = _mm512_mullo_epi32(_mm512_add_epi32(b[2], ione), sz);
    return c;
}

/* corner c's table offsets (its index times F) and trilinear weight, for the 16 lanes */
static inline __attribute__((always_inline)) __m512i
corner16(const cells16 *p, int c, int dense, uint32_t mask, const int32_t F, __m512 *w) {
    const int ix = c >> 2, iy = (c >> 1) & 1, iz = c & 1;
    const __m512i X = p->tx[ix], Y = p->ty[iy], Z = p->tz[iz];
    __m512i id = dense ? _mm512_add_epi32(_mm512_add_epi32(X, Y), Z)
                       : _mm512_and_si512(_mm512_xor_si512(_mm512_xor_si512(X, Y), Z),
                                          _mm512_set1_epi32((int32_t)mask));
    *w = _mm512_mul_ps(_mm512_mul_ps(p->w[0][ix], p->w[1][iy]), p->w[2][iz]);
    return F == 1 ? id : F == 2 ? _mm512_add_epi32(id, id)
                                : _mm512_mullo_epi32(id, _mm512_set1_epi32(F));
}

static inline __attribute__((always_inline)) __m512i strided16(int64_t stride) {
    return _mm512_mullo_epi32(
        _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15),
        _mm512_set1_epi32((int32_t)stride));
}

static inline __attribute__((always_inline)) __mmask16 lanes16(int64_t left) {
    return left >= 16 ? (__mmask16)0xFFFF : (__mmask16)((1u << left) - 1u);
}

/* both features of 16 table entries (F = 2): two 64-bit gathers of 8 entries each, split
 * into the features' lanes (f0, f1) — half the gathered elements of one gather per feature */
static inline __attribute__((always_inline)) void
pairs16(const float *t, __m512i id, __mmask16 k, __m512 *f0, __m512 *f1) {
    const __m512d z = _mm512_setzero_pd();
    const __m512 lo = _mm512_castpd_ps(_mm512_mask_i32gather_pd(
        z, (__mmask8)k, _mm512_castsi512_si256(id), t, 8));
    const __m512 hi = _mm512_castpd_ps(_mm512_mask_i32gather_pd(
        z, (__mmask8)(k >> 8), _mm512_extracti64x4_epi64(id, 1), t, 8));
    const __m512i even = _mm512_setr_epi32(0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24, 26,
                                           28, 30);
    *f0 = _mm512_permutex2var_ps(lo, even, hi);
    *f1 = _mm512_permutex2var_ps(lo, _mm512_add_epi32(even, _mm512_set1_epi32(1)), hi);
}

static inline __attribute__((always_inline)) void
level_simd(const float *x, int64_t n, const int32_t F, int64_t r, int dense, uint32_t mask,
           const float *t, float *out, int64_t out_stride) {
    const __m512 zero = _mm512_setzero_ps();
    const __m512i ost = strided16(out_stride);
    for (int64_t i = 0; i < n; i += 16) {
        const int64_t m = n - i >= 16 ? 16 : n - i;
        const __mmask16 k = lanes16(m);
        const cells16 p = locate16(x + 3 * i, m, r, dense);
        float *op = out + i * out_stride;
        if (F >= 3) {
            /* an entry's F features are one (masked) vector load: per point, 8 loads
             * instead of 8·F gathered elements (the expression grid's 16 features, the
             * warp bake's 3); the same multiply-adds in the same order */
            const __mmask16 fm = F >= 16 ? (__mmask16)0xFFFF : (__mmask16)((1u << F) - 1u);
            int32_t ids[8][16];
            float ws[8][16];
            for (int c = 0; c < 8; c++) {
                __m512 w;
                _mm512_storeu_si512(ids[c], corner16(&p, c, dense, mask, F, &w));
                _mm512_storeu_ps(ws[c], w);
            }
            for (int64_t q = 0; q < m; q++) {
                __m512 acc = zero;
                for (int c = 0; c < 8; c++)
                    acc = _mm512_fmadd_ps(_mm512_maskz_loadu_ps(fm, t + ids[c][q]),
                                          _mm512_set1_ps(ws[c][q]), acc);
                _mm512_mask_storeu_ps(op + q * out_stride, fm, acc);
            }
            continue;
        }
        if (F == 2) {
            __m512 a0 = zero, a1 = zero;
            for (int c = 0; c < 8; c++) {
                __m512 w, f0, f1;
                pairs16(t, corner16(&p, c, dense, mask, 1, &w), k, &f0, &f1);
                a0 = _mm512_fmadd_ps(f0, w, a0);
                a1 = _mm512_fmadd_ps(f1, w, a1);
            }
            /* each point's two features side by side again, one 64-bit store per point */
            const __m512i lo = _mm512_setr_epi32(0, 16, 1, 17, 2, 18, 3, 19, 4, 20, 5, 21, 6,
                                                 22, 7, 23);
            const __m256i rows = _mm512_castsi512_si256(ost);
            _mm512_mask_i32scatter_pd(op, (__mmask8)k, rows,
                                      _mm512_castps_pd(_mm512_permutex2var_ps(a0, lo, a1)), 4);
            _mm512_mask_i32scatter_pd(op + 8 * out_stride, (__mmask8)(k >> 8), rows,
                                      _mm512_castps_pd(_mm512_permutex2var_ps(
                                          a0, _mm512_add_epi32(lo, _mm512_set1_epi32(8)), a1)),
                                      4);
            continue;
        }
        __m512 acc[SIMD_MAX_F];
        for (int32_t j = 0; j < F; j++) acc[j] = zero;
        for (int c = 0; c < 8; c++) {
            __m512 w;
            const __m512i id = corner16(&p, c, dense, mask, F, &w);
            for (int32_t j = 0; j < F; j++)
                acc[j] = _mm512_fmadd_ps(_mm512_mask_i32gather_ps(zero, k, id, t + j, 4), w,
                                         acc[j]);
        }
        for (int32_t j = 0; j < F; j++) _mm512_mask_i32scatter_ps(op + j, k, ost, acc[j], 4);
    }
}
/* with the feature count a constant where it is small, so that the accumulators stay in
 * registers (a variable count cost the 2-feature grid ~25 %) */
static void level_any(const float *x, int64_t n, int32_t F, int64_t r, int dense,
                      uint32_t mask, const float *t, float *out, int64_t out_stride) {
    switch (F) {
    case 1: level_simd(x, n, 1, r, dense, mask, t, out, out_stride); break;
    case 2: level_simd(x, n, 2, r, dense, mask, t, out, out_stride); break;
    case 3: level_simd(x, n, 3, r, dense, mask, t, out, out_stride); break;
    case 4: level_simd(x, n, 4, r, dense, mask, t, out, out_stride); break;
    case 16: level_simd(x, n, 16, r, dense, mask, t, out, out_stride); break;
    default: level_simd(x, n, F, r, dense, mask, t, out, out_stride);
    }
}
#endif

/* The generic loop of one level for n points: rows `out_stride` floats apart. */
static void level_generic(const float *x, int64_t n, int32_t F, int64_t r, int dense,
                          int64_t hash_mask, const float *t, float *out, int64_t out_stride) {
    for (int64_t i = 0; i < n; i++) {
        int64_t idx[8];
        float fr[3], w[8];
        int inside[3];
        locate(x + 3 * i, r, dense, hash_mask, idx, fr, inside);
        weights(fr, w);
        for (int32_t f = 0; f < F; f++) {
            float acc = 0.0f;
            for (int c = 0; c < 8; c++) acc += t[idx[c] * F + f] * w[c];
            out[i * out_stride + f] = acc;
        }
    }
}

/* One level for a block of points, by the vector path where it applies. */
static void level_block(const float *x, int64_t n, int32_t F, int64_t r, int dense,
                        int64_t hash_mask, const float *t, float *out, int64_t out_stride) {
#ifdef HAVE_LEVEL_SIMD
    const int64_t entries = dense ? (r + 1) * (r + 1) * (r + 1) : hash_mask + 1;
    if (F <= SIMD_MAX_F && entries * F < (1LL << 31) && r < (1LL << 20)
            && 16 * out_stride < (1LL << 31)) {
        level_any(x, n, F, r, dense, (uint32_t)hash_mask, t, out, out_stride);
        return;
    }
#endif
    level_generic(x, n, F, r, dense, hash_mask, t, out, out_stride);
}

/* The expression feature fields: each level's F = R·Fe features read as (R, Fe) and
 * contracted with the point's z (R,), out (N, L·Fe) with rows `out_stride` floats apart:
 * Σ_r z_r G_r(x). A block's features of one level go through a small scratch buffer that
 * stays in cache, so that the (N, L·F) features are never written out (8x the output for
 * `fast`'s fields) and no batched product of tiny matrices runs over them (together a third
 * of a face ray's time at inference on the 2-core CPU: docs/results.md). Level-major like
 * the forward pass; each output a fixed-order sum. F <= CONTRACT_MAX_F (the caller checks). */
#define CONTRACT_BLOCK 512
#define CONTRACT_MAX_F 64
void hashgrid_contract(const float *x, int64_t n, int32_t L, int32_t F,
                       const float *const *tables, const int64_t *res, const uint8_t *dense,
                       int64_t hash_mask, const float *z, int32_t R, float *out,
                       int64_t out_stride, int32_t threads) {
    const int32_t Fe = F / R;
    for (int32_t l = 0; l < L; l++) {
#pragma omp parallel for schedule(static) num_threads(threads)
        for (int64_t lo = 0; lo < n; lo += CONTRACT_BLOCK) {
            float scratch[CONTRACT_BLOCK * CONTRACT_MAX_F];
            const int64_t m = lo + CONTRACT_BLOCK < n ? CONTRACT_BLOCK : n - lo;
            level_block(x + 3 * lo, m, F, res[l], dense[l], hash_mask, tables[l], scratch, F);
            for (int64_t q = 0; q < m; q++) {
                const float *zq = z + (lo + q) * R, *sq = scratch + q * F;
                float *oq = out + (lo + q) * out_stride + l * Fe;
                for (int32_t e = 0; e < Fe; e++) {
                    float acc = 0.0f;
                    for (int32_t r = 0; r < R; r++) acc += zq[r] * sq[r * Fe + e];
                    oq[e] = acc;
                }
            }
        }
    }
}

void hashgrid_forward(const float *x, int64_t n, int32_t L, int32_t F,
                      const float *const *tables, const int64_t *res,
                      const uint8_t *dense, int64_t hash_mask, float *out, int64_t out_stride,
                      int32_t threads) {
    /* level-major: one level's table stays in cache while every point reads it */
    const int64_t block = 4096; /* a multiple of 16 */
    for (int32_t l = 0; l < L; l++) {
#pragma omp parallel for schedule(static) num_threads(threads)
        for (int64_t lo = 0; lo < n; lo += block)
            level_block(x + 3 * lo, lo + block < n ? block : n - lo, F, res[l], dense[l],
                        hash_mask, tables[l], out + lo * out_stride + l * F, out_stride);
    }
}

#ifdef HAVE_LEVEL_SIMD
/* One level of the backward pass for 16 points at a time: the cell, corner indices and
 * weights as in `level_simd`, the position gradient in vector lanes; the table's gradient
 * is still added one point, corner and feature at a time in the generic loop's order
 * (a vector scatter-add would need conflict handling, and that order keeps the result
 * bit-identical to the generic loop and independent of the thread count). */
static inline __attribute__((always_inline)) void
level_back_simd(const float *x, int64_t n, const int32_t F, int64_t gstride, int64_t r,
                int dense, uint32_t mask, const float *t, const float *gout, float *gt,
                float *gl) {
    const __m512 zero = _mm512_setzero_ps(), rf = _mm512_set1_ps((float)r);
    const __m512i gst = strided16(gstride), in3 = strided16(3);
    int32_t ids[8][16];
    float ws[8][16];
    for (int64_t i = 0; i < n; i += 16) {
        const int64_t m = n - i >= 16 ? 16 : n - i;
        const __mmask16 k = lanes16(m);
        const cells16 p = locate16(x + 3 * i, m, r, dense);
        const float *go = gout + i * gstride;
        __m512 dx = zero, dy = zero, dz = zero;
        __m512 gv[SIMD_MAX_F];
        if (gl)
            for (int32_t j = 0; j < F; j++)
                gv[j] = _mm512_mask_i32gather_ps(zero, k, gst, go + j, 4);
        for (int c = 0; c < 8; c++) {
            const int ix = c >> 2, iy = (c >> 1) & 1, iz = c & 1;
            __m512 w;
            const __m512i id = corner16(&p, c, dense, mask, F, &w);
            if (gt) {
                _mm512_storeu_si512(ids[c], id);
                _mm512_storeu_ps(ws[c], w);
            }
            if (gl) {
                /* s_c = sum_f gout_f * table_f[idx_c], then the corner's share of each slope */
                __m512 sc = zero;
                if (F == 2) {
                    __m512 w1, f0, f1;
                    pairs16(t, corner16(&p, c, dense, mask, 1, &w1), k, &f0, &f1);
                    sc = _mm512_fmadd_ps(gv[1], f1, _mm512_fmadd_ps(gv[0], f0, sc));
                } else {
                    for (int32_t j = 0; j < F; j++)
                        sc = _mm512_fmadd_ps(gv[j],
                                             _mm512_mask_i32gather_ps(zero, k, id, t + j, 4), sc);
                }
                const __m512 sx = ix ? sc : _mm512_sub_ps(zero, sc);
                const __m512 sy = iy ? sc : _mm512_sub_ps(zero, sc);
                const __m512 sz = iz ? sc : _mm512_sub_ps(zero, sc);
                dx = _mm512_fmadd_ps(sx, _mm512_mul_ps(p.w[1][iy], p.w[2][iz]), dx);
                dy = _mm512_fmadd_ps(sy, _mm512_mul_ps(p.w[0][ix], p.w[2][iz]), dy);
                dz = _mm512_fmadd_ps(sz, _mm512_mul_ps(p.w[0][ix], p.w[1][iy]), dz);
            }
        }
        if (gl) {
            /* the reference clamps x to [0, 1]: no gradient outside */
            float *gp = gl + 3 * i;
            _mm512_mask_i32scatter_ps(gp + 0, k, in3, _mm512_maskz_mul_ps(p.inside[0], dx, rf), 4);
            _mm512_mask_i32scatter_ps(gp + 1, k, in3, _mm512_maskz_mul_ps(p.inside[1], dy, rf), 4);
            _mm512_mask_i32scatter_ps(gp + 2, k, in3, _mm512_maskz_mul_ps(p.inside[2], dz, rf), 4);
        }
        if (gt)
            for (int64_t q = 0; q < m; q++) {
                const float *g = go + q * gstride;
                for (int c = 0; c < 8; c++) {
                    float *e = gt + ids[c][q];
                    const float wc = ws[c][q];
                    for (int32_t j = 0; j < F; j++) e[j] += g[j] * wc;
                }
            }
    }
}
static void level_back_any(const float *x, int64_t n, int32_t F, int64_t gstride, int64_t r,
                           int dense, uint32_t mask, const float *t, const float *gout,
                           float *gt, float *gl) {
    switch (F) {
    case 1: level_back_simd(x, n, 1, gstride, r, dense, mask, t, gout, gt, gl); break;
    case 2: level_back_simd(x, n, 2, gstride, r, dense, mask, t, gout, gt, gl); break;
    case 4: level_back_simd(x, n, 4, gstride, r, dense, mask, t, gout, gt, gl); break;
    default: level_back_simd(x, n, F, gstride, r, dense, mask, t, gout, gt, gl);
    }
}
#endif

/* gtables[l] (T_l, F), zero-filled by the caller, or NULL to skip a level (or the whole
 * array NULL); gx (N, 3) or NULL, with scratch (L, N, 3) for the per-level position
 * gradients, which are summed afterwards in level order so that the result does not
 * depend on which thread ran which level. */
void hashgrid_backward(const float *x, int64_t n, int32_t L, int32_t F,
                       const float *const *tables, const int64_t *res,
                       const uint8_t *dense, int64_t hash_mask, const float *gout,
                       float *const *gtables, float *gx, float *scratch, int32_t threads) {
    /* one pass per level, levels in parallel: the table entries read for the position
     * gradient and the gradient entries written are at the same indices */
#pragma omp parallel for schedule(dynamic, 1) num_threads(threads)
    for (int32_t l = 0; l < L; l++) {
        const float *t = tables[l];
        float *gt = gtables ? gtables[l] : 0;
        float *gl = gx ? scratch + (int64_t)l * n * 3 : 0;
        const float r = (float)res[l];
        if (!gt && !gl) continue;
#ifdef HAVE_LEVEL_SIMD
        const int64_t entries = dense[l] ? (res[l] + 1) * (res[l] + 1) * (res[l] + 1)
                                         : hash_mask + 1;
        if (F <= SIMD_MAX_F && entries * F < (1LL << 31) && res[l] < (1LL << 20)
                && 16 * (int64_t)L * F < (1LL << 31)) {
            level_back_any(x, n, F, (int64_t)L * F, res[l], dense[l], (uint32_t)hash_mask, t,
                           gout + l * F, gt, gl);
            continue;
        }
#endif
        for (int64_t i = 0; i < n; i++) {
            int64_t idx[8];
            float fr[3], w[8];
            int inside[3];
            locate(x + 3 * i, res[l], dense[l], hash_mask, idx, fr, inside);
            const float *go = gout + i * L * F + l * F;
            if (gt) {
                weights(fr, w);
                for (int c = 0; c < 8; c++)
                    for (int32_t f = 0; f < F; f++) gt[idx[c] * F + f] += go[f] * w[c];
            }
            if (gl) {
                /* s_c = sum_f gout_f * table_f[idx_c]: the loss's slope along corner c */
                float s[8];
                for (int c = 0; c < 8; c++) {
                    float acc = 0.0f;
                    for (int32_t f = 0; f < F; f++) acc += go[f] * t[idx[c] * F + f];
                    s[c] = acc;
                }
                float wx[2] = {1.0f - fr[0], fr[0]}, wy[2] = {1.0f - fr[1], fr[1]},
                      wz[2] = {1.0f - fr[2], fr[2]};
                float dx = 0.0f, dy = 0.0f, dz = 0.0f;
                for (int c = 0; c < 8; c++) {
                    int ix = c >> 2, iy = (c >> 1) & 1, iz = c & 1;
                    dx += s[c] * (ix ? 1.0f : -1.0f) * wy[iy] * wz[iz];
                    dy += s[c] * (iy ? 1.0f : -1.0f) * wx[ix] * wz[iz];
                    dz += s[c] * (iz ? 1.0f : -1.0f) * wx[ix] * wy[iy];
                }
                /* the reference clamps x to [0, 1]: no gradient outside */
                gl[3 * i + 0] = inside[0] ? dx * r : 0.0f;
                gl[3 * i + 1] = inside[1] ? dy * r : 0.0f;
                gl[3 * i + 2] = inside[2] ? dz * r : 0.0f;
            }
        }
    }
    if (gx) {
#pragma omp parallel for schedule(static) num_threads(threads)
        for (int64_t j = 0; j < 3 * n; j++) {
            float acc = 0.0f;
            for (int32_t l = 0; l < L; l++) acc += scratch[(int64_t)l * n * 3 + j];
            gx[j] = acc;
        }
    }
}
