"""The Triton kernels (gpu_kernels.py) against their PyTorch references, run by Triton's
interpreter on the CPU: the same kernel code a GPU compiles, without a GPU. The interpreter
is chosen when Triton is imported, so the checks run in a fresh process."""

import importlib.util
import os
import subprocess
import sys
import textwrap

import pytest

pytestmark = pytest.mark.skipif(importlib.util.find_spec("triton") is None,
                                reason="Triton is not installed (the test extra installs it)")

CHECK = textwrap.dedent("""
    import torch
    from flamenerf import gpu_kernels as gk
    from flamenerf.meshes import nearest_vertices, nearest_vertices_brute
    from flamenerf.model.encodings import HashGrid

    assert gk.available(torch.device("cpu"))
    torch.manual_seed(0)
    # every level kind (dense, hashed), feature widths that are and are not powers of two,
    # points on the grid's faces and outside it (clamped)
    for L, F, log2, base, top in ((6, 2, 12, 4, 64), (4, 8, 10, 4, 32), (3, 3, 10, 8, 40)):
        grid = HashGrid(L, F, log2, base, top)
        for t in grid.tables:
            t.data.uniform_(-1, 1)
        x = torch.rand(700, 3)
        x[0], x[1], x[2, 0], x[3, 1] = 1.0, 0.0, 1.2, -0.3
        ref = grid.forward_grouped(x)
        assert (gk.hashgrid_forward(grid, x) - ref).abs().max() < 1e-6
        # into columns of a wider buffer, the others untouched
        buf = torch.full((700, L * F + 7), 5.0)
        gk.hashgrid_forward(grid, x, buf[:, 3:3 + L * F])
        assert (buf[:, 3:3 + L * F] - ref).abs().max() < 1e-6
        assert bool((buf[:, :3] == 5).all() and (buf[:, 3 + L * F:] == 5).all())
        # half precision stored by the kernel itself (the GPU inference path's features)
        half = torch.full((700, L * F + 2), 5.0, dtype=torch.float16)
        grid.encode_into(x, half[:, 1:1 + L * F])
        assert (half[:, 1:1 + L * F].float() - ref).abs().max() < 2e-3 * ref.abs().max()
        assert bool((half[:, 0] == 5).all() and (half[:, -1] == 5).all())
        grid.tables[0].data.add_(0.5)  # a table changed between calls (a training step)
        assert (gk.hashgrid_forward(grid, x) - grid.forward_grouped(x)).abs().max() < 1e-6

    # the expression fields' contraction inside the kernel: Σ_r z_r G_r(x) per level,
    # ranks and widths with and without padding
    for L, R, Fe in ((3, 8, 2), (2, 3, 2), (2, 4, 1)):
        grid = HashGrid(L, R * Fe, 10, 4, 32)
        for t in grid.tables:
            t.data.uniform_(-1, 1)
        x, z = torch.rand(300, 3), torch.randn(300, R)
        z = z.half()  # as autocast gives it
        ref = torch.matmul(z.float()[:, None, None, :],
                           grid.forward_grouped(x).view(-1, L, R, Fe)).reshape(-1, L * Fe)
        got = gk.hashgrid_contract(grid, x, z, Fe)
        assert got.shape == ref.shape and got.dtype == torch.float32
        assert (got - ref).abs().max() < 1e-5 * max(1.0, float(ref.abs().max()))

    # a hash field's two heads in one kernel, in half precision (the GPU's inference path)
    # against the float32 MLPs: 48 features -> 64 -> σ + 15, then (15 + per-ray 35) -> 64
    # -> 64 -> RGB, four samples a ray
    from flamenerf.model.mlp import MLP
    torch.manual_seed(0)
    dh, ch = MLP(48, 64, 1, (), out_dim=16), MLP(15 + 35, 64, 2, (), out_dim=3)
    feats, cond = torch.randn(203, 48), torch.randn(51, 35)
    first = ch.layers[0]
    with torch.no_grad():
        g = dh(feats)
        sig_ref = torch.exp(g[:, 0].clamp(max=15))
        rgb_ref = torch.sigmoid(ch(g[:, 1:], cond.repeat_interleave(4, 0)[:203]))
        term = torch.nn.functional.linear(cond, first.weight[:, 15:], first.bias)
        sig, rgb = gk.field_heads(feats.half(), term, 4, dh, ch)
        assert sig.dtype == rgb.dtype == torch.float32 and rgb.shape == (203, 3)
        assert (rgb - rgb_ref).abs().max() < 1e-2, (rgb - rgb_ref).abs().max()
        assert ((sig - sig_ref).abs() / sig_ref).max() < 2e-2
        for block in (None, 128):  # the default, and a block of another size
            sig32, rgb32 = gk.field_heads(feats, term, 4, dh, ch, block=block)  # float32
            assert (rgb32 - rgb_ref).abs().max() < 1e-5, block
            assert torch.allclose(sig32, sig_ref, rtol=1e-4), block
        # a hidden width under DOT_MIN is padded with units that stay 0
        dh2, ch2 = MLP(48, 32, 1, (), out_dim=16), MLP(15 + 35, 32, 2, (), out_dim=3)
        term2 = torch.nn.functional.linear(cond, ch2.layers[0].weight[:, 15:],
                                           ch2.layers[0].bias)
        g2 = dh2(feats)
        sig2, rgb2 = gk.field_heads(feats, term2, 4, dh2, ch2)
        assert (rgb2 - torch.sigmoid(ch2(g2[:, 1:], cond.repeat_interleave(4, 0)[:203]))
                ).abs().max() < 1e-5
        assert torch.allclose(sig2, torch.exp(g2[:, 0].clamp(max=15)), rtol=1e-4)
        try:  # blocks of 32: dots of that size fault on sm_90 (DOT_MIN)
            gk.field_heads(feats, term, 4, dh, ch, block=32)
            raise AssertionError("a block of 32 was taken")
        except ValueError as e:
            assert "power of two" in str(e)
        # heads of another shape are left to PyTorch
        assert gk.field_heads(feats, term, 4, MLP(48, 64, 2, (), out_dim=16), ch) is None

    # k nearest vertices of each point's own mesh: the k-d tree's answer
    g = torch.Generator().manual_seed(1)
    meshes = torch.rand(3, 50, 3, generator=g)
    pts = torch.rand(300, 3, generator=g)
    which = torch.randint(3, (300,), generator=g)
    for k in (1, 3, 4, 8):
        d, i = gk.knn(pts, meshes, which, k)
        td, ti = nearest_vertices(pts, meshes, k, 10.0, which)
        assert (d - td).abs().max() < 1e-6 and torch.equal(i, ti), k
        assert bool((i // 50 == which[:, None]).all())
    # a face-sized mesh (vertex tiles of 8 and 16: 700 = 87 or 43 whole tiles and a part)
    # and points along rays through it, as an image's samples come: most tiles are
    # skipped; and no tiles (every vertex in turn)
    big = torch.rand(1, 700, 3, generator=g)
    ray = torch.rand(40, 1, 3, generator=g) + torch.linspace(-0.5, 0.5, 20)[None, :, None]
    ray = ray.reshape(-1, 3)
    for k, tile, n in ((1, None, 800), (8, None, 800), (4, 0, 128), (4, 16, 128)):
        # (the other choices on one block of points: the interpreter is slow)
        d, i = gk.knn(ray[:n], big, torch.zeros(n, dtype=torch.long), k, tile=tile)
        td, ti = nearest_vertices(ray[:n], big[0], k, 10.0)
        assert (d - td).abs().max() < 1e-6 and torch.equal(i, ti), (k, tile)
    # the brute-force path off the CPU takes the kernel where it runs: the rays form and
    # the bound as the tree has them
    rays, ray_mesh = pts.view(30, 10, 3), torch.randint(3, (30,), generator=g)
    for k in (1, 4):
        bd, bi = nearest_vertices_brute(rays, meshes, k, 0.2, ray_mesh)
        td, ti = nearest_vertices(rays, meshes, k, 0.2, ray_mesh)
        fin = torch.isfinite(td)
        assert bool(fin.any() and (~fin).any()) and torch.equal(fin, torch.isfinite(bd))
        assert (bd[fin] - td[fin]).abs().max() < 1e-6 and torch.equal(bi, ti)
    print("kernels agree")
""")


@pytest.mark.slow
def test_triton_kernels_match_their_references_under_the_interpreter():
    env = {**os.environ, "TRITON_INTERPRET": "1", "FLAMENERF_GPU_KERNELS": "1"}
    out = subprocess.run([sys.executable, "-c", CHECK], env=env, capture_output=True,
                         text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "kernels agree" in out.stdout


def test_without_a_gpu_or_the_interpreter_the_kernels_stand_aside():
    import torch

    from flamenerf import gpu_kernels

    if os.environ.get("TRITON_INTERPRET") == "1":
        pytest.skip("this process runs Triton's interpreter")
    assert not gpu_kernels.available(torch.device("cpu"))


def test_a_kernel_that_cannot_be_built_gives_way_to_pytorch(monkeypatch):
    """A GPU or driver Triton cannot compile a kernel for: one warning, the PyTorch path's
    answer, and that kernel off from then on (never a crash in a render); the other kernels
    go on."""
    import torch

    from flamenerf import gpu_kernels
    from flamenerf.meshes import nearest_vertices, nearest_vertices_brute
    from flamenerf.model.encodings import HashGrid

    class Unbuildable:
        def __getitem__(self, grid):
            def launch(*args, **meta):
                raise RuntimeError("no compiler for this device")
            return launch

    monkeypatch.setenv("TRITON_INTERPRET", "1")  # lets the CPU stand in for the GPU
    monkeypatch.setattr(gpu_kernels, "_tried", True)
    monkeypatch.setattr(gpu_kernels, "_kernels", {"knn": Unbuildable(),
                                                  "hashgrid": Unbuildable()})
    g = torch.Generator().manual_seed(0)
    meshes, pts = torch.rand(2, 30, 3, generator=g), torch.rand(50, 3, generator=g)
    which = torch.randint(2, (50,), generator=g)
    with pytest.warns(UserWarning, match="knn failed"):
        d, i = nearest_vertices_brute(pts, meshes, 4, 10.0, which)
    td, ti = nearest_vertices(pts, meshes, 4, 10.0, which)
    assert torch.allclose(d, td, atol=1e-6) and torch.equal(i, ti)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # once: no second warning, no second try
        assert gpu_kernels.knn(pts, meshes, which, 4) is None
        d2, i2 = nearest_vertices_brute(pts, meshes, 4, 10.0, which)
    assert torch.equal(i2, ti)
    grid = HashGrid(3, 2, 10, 4, 32)
    x = torch.rand(40, 3, generator=g)
    with pytest.warns(UserWarning, match="hashgrid failed"):  # still tried: its own failure
        assert gpu_kernels.hashgrid_forward(grid, x) is None


def test_a_kernel_that_faults_the_gpu_stops_the_work(monkeypatch):
    """A fault ends the CUDA context: PyTorch's ops would fail after it, so the kernel does
    not fall back as an unbuildable one does; the error names it."""
    import torch

    from flamenerf import gpu_kernels
    from flamenerf.model.encodings import HashGrid

    class Faulting:
        def __getitem__(self, grid):
            def launch(*args, **meta):
                raise RuntimeError("Triton Error [CUDA]: an illegal memory access was "
                                   "encountered")
            return launch

    monkeypatch.setenv("TRITON_INTERPRET", "1")
    monkeypatch.setattr(gpu_kernels, "_tried", True)
    monkeypatch.setattr(gpu_kernels, "_kernels", {"hashgrid": Faulting()})
    with pytest.raises(gpu_kernels.GPUFault, match="launch of the Triton kernel hashgrid"):
        gpu_kernels.hashgrid_forward(HashGrid(3, 2, 10, 4, 32), torch.rand(40, 3))
    assert gpu_kernels.gpu_faulted(RuntimeError("CUDA error: an illegal memory access"))
    assert not gpu_kernels.gpu_faulted(RuntimeError("no compiler for this device"))


def test_the_kernels_named_in_the_environment(monkeypatch):
    """FLAMENERF_GPU_KERNELS: unset leaves the unproven kernels (none now) off, 1 turns every
    one on, a list keeps those named, a name that is no kernel is one clear error."""
    import torch

    from flamenerf import gpu_kernels
    from flamenerf.errors import UserError

    if importlib.util.find_spec("triton") is not None:
        assert tuple(gpu_kernels._define()) == gpu_kernels.NAMES
    every = {"hashgrid": 1, "knn": 2, "field_heads": 3}
    monkeypatch.setattr(gpu_kernels, "_define", lambda: dict(every))
    monkeypatch.setattr(gpu_kernels, "_kernels", None)  # restored after: _load sets it

    def loaded(value):
        monkeypatch.setattr(gpu_kernels, "_tried", False)
        if value is None:
            monkeypatch.delenv("FLAMENERF_GPU_KERNELS", raising=False)
        else:
            monkeypatch.setenv("FLAMENERF_GPU_KERNELS", value)
        return set(gpu_kernels._load())

    assert loaded(None) == loaded("") == set(every) - gpu_kernels.UNPROVEN
    assert loaded("1") == set(every)
    assert loaded("knn, field_heads") == {"knn", "field_heads"}
    with pytest.raises(UserError, match="no kernel knnn"):
        loaded("knnn,hashgrid")
    assert not gpu_kernels._tried  # nothing kept from the wrong name: it raises again
    with pytest.raises(UserError):
        gpu_kernels._load()
    monkeypatch.setenv("FLAMENERF_GPU_KERNELS", "0")
    assert gpu_kernels.working() == [] and not gpu_kernels.available(torch.device("cuda"))
    assert "were off" in gpu_kernels.fault_advice()


def test_the_kernel_check_tries_each_configuration_once_and_keeps_the_largest_right():
    """benchmarks/gpu_kernel_check.py's choices (workflows/kernel_check.py), which the next
    GPU call runs first: the padded heads alone are among its renders (a first version
    dropped them), nothing twice, and the set it hands on is the largest that rendered right
    at every size."""
    from flamenerf.workflows import kernel_check as g

    configs = g.FIRST + g.BISECT
    labels = [c[0] for c in configs]
    assert {"off", "all", "default", "field_heads alone", "field_heads widths of 16"} <= set(
        labels)
    assert len({(g.kernel_set(c[1]), c[2]) for c in configs}) == len(configs)

    def row(env, right, heads=""):
        return {"env": env, "heads": heads, "right": right}

    assert g.best_set([row("0", True), row("1", True), row("", True)]) == "1"
    assert g.best_set([row("0", True), row("1", False), row("", True),
                       row("field_heads", False, "64,4,16")]) == g.DEFAULT
    assert g.best_set([row("0", True), row("1", False), row("", False), row("knn", True),
                       row("hashgrid", False)]) == "knn"
    assert g.best_set([row("0", True), row("1", True), row("", True, ""),
                       row("1", False)]) == g.DEFAULT  # wrong at a second size
    assert g.best_set([row("0", True), row("1", False)]) == "0"
