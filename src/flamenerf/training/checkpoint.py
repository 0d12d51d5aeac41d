"""Checkpoints: one dict per `step-000001000.ckpt`, written atomically, last K kept.

A checkpoint holds tensors and plain Python values only (numbers, strings, lists, dicts),
so it loads with `torch.load(weights_only=True)`, which cannot run code: runs are shared
between people, and a pickle can do anything when loaded. Checkpoints of flamenerf 0.1
pickled NumPy's and Python's RNG states; they are refused with a line naming
`flamenerf convert`, which rewrites them for a user who trusts their source.
"""

from __future__ import annotations

import pickle
import random
import re
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from flamenerf.config import is_int, is_number
from flamenerf.errors import UserError, warn
from flamenerf.io import atomic_write_bytes

_PAT = re.compile(r"step-(\d{9})\.ckpt$")
# what an older flamenerf left after a kill -9 (no PID in the name): `.step-...ckpt.XXXXXXXX`
LEGACY_TEMP = re.compile(r"\.step-\d{9}\.ckpt\.[a-z0-9_]{8}")
FORMAT = 2  # 1: flamenerf 0.1, RNG states pickled
# the globals flamenerf 0.1's pickled RNG states name (NumPy's arrays and dtypes, and the
# tuple of Python's state): only a file that needs these may be offered `convert --trust`
LEGACY_GLOBALS = ("numpy.", "_codecs.encode", "builtins.tuple", "collections.OrderedDict")
REQUIRED = ("step", "model", "model_args", "optimizer", "generator", "torch_rng",
            "numpy_rng", "python_rng")


# ----------------------------------------------------------------------------- RNG state


def rng_states(gen: torch.Generator) -> dict[str, Any]:
    """Every random stream training draws from, as tensors and plain values."""
    kind, keys, pos, has_gauss, gauss = np.random.get_state()
    version, mt, gauss_next = random.getstate()
    return {
        "generator": gen.get_state(),
        "torch_rng": torch.get_rng_state(),
        "numpy_rng": {"kind": str(kind), "keys": torch.from_numpy(keys.astype(np.int64)),
                      "pos": int(pos), "has_gauss": int(has_gauss), "gauss": float(gauss)},
        "python_rng": {"version": int(version), "state": torch.tensor(mt, dtype=torch.int64),
                       "gauss_next": gauss_next},
    }


def set_rng_states(st: dict[str, Any], gen: torch.Generator,
                   path: Path | str = "checkpoint") -> None:
    """Restore what `rng_states` saved; a state the generators refuse is a one-line error
    naming the checkpoint `path` (load_checkpoint checks their shapes, not every value)."""
    try:
        gen.set_state(st["generator"])
        torch.set_rng_state(st["torch_rng"])
        n = st["numpy_rng"]
        np.random.set_state((n["kind"], n["keys"].numpy().astype(np.uint32), n["pos"],
                             n["has_gauss"], n["gauss"]))
        p = st["python_rng"]
        random.setstate((p["version"], tuple(p["state"].tolist()), p["gauss_next"]))
    except (KeyError, TypeError, ValueError, RuntimeError, IndexError, AttributeError,
            OverflowError) as e:
        raise UserError(f"{path}: not a readable checkpoint (damaged random-number state: "
                        f"{_first_sentence(e)})") from None


# ----------------------------------------------------------------------------- sparse moments

# Adam's two moments are as large as the parameters, and for a hash table most of them are
# exactly zero: rows (table entries) that no sample point has reached yet. Only rows with a
# nonzero bit in either moment are stored, with a bit mask of which; loading puts back zeros,
# so the state is bit-identical. Measured on the `fast` preset (2^19-entry tables), 32 px
# scene: 62% of the rows touched after 20-60 steps, the checkpoint 97.6 -> 74 MB.
SPARSE_MIN_ROWS = 1024  # smaller tensors are not worth a mask


def _nonzero_rows(t: torch.Tensor) -> torch.Tensor:
    """Rows with any nonzero bit (so -0.0 and NaN count as nonzero: exact round trip)."""
    return (t.detach().contiguous().view(torch.uint8).reshape(t.shape[0], -1) != 0).any(1)


def pack_moments(opt_state: dict[str, Any]) -> dict[str, Any]:
    state = {}
    for i, s in opt_state["state"].items():
        m, v = s.get("exp_avg"), s.get("exp_avg_sq")
        if m is None or v is None or m.dim() < 2 or m.shape[0] < SPARSE_MIN_ROWS:
            state[i] = s
            continue
        keep = _nonzero_rows(m) | _nonzero_rows(v)
        bits = np.packbits(keep.cpu().numpy())
        state[i] = {**s, "exp_avg": m[keep], "exp_avg_sq": v[keep],
                    "sparse_rows": torch.from_numpy(bits), "num_rows": int(m.shape[0])}
    return {**opt_state, "state": state}


def unpack_moments(opt_state: dict[str, Any]) -> dict[str, Any]:
    state = {}
    for i, s in opt_state["state"].items():
        if "sparse_rows" not in s:
            state[i] = s
            continue
        s = dict(s)
        n = s.pop("num_rows")
        keep = torch.from_numpy(np.unpackbits(s.pop("sparse_rows").numpy(), count=n)
                                .astype(bool))
        for k in ("exp_avg", "exp_avg_sq"):
            rows = s[k]
            full = torch.zeros((n, *rows.shape[1:]), dtype=rows.dtype)
            full[keep] = rows
            s[k] = full
        state[i] = s
    return {**opt_state, "state": state}


# ----------------------------------------------------------------------------- files


def checkpoints(run_dir: Path) -> list[Path]:
    """The run's checkpoints, oldest first."""
    ckdir = Path(run_dir) / "checkpoints"
    if not ckdir.is_dir():
        return []
    return sorted(p for p in ckdir.iterdir() if _PAT.fullmatch(p.name))


def checkpoint_step(path: Path) -> int:
    return int(_PAT.search(path.name).group(1))


def latest_checkpoint(run_dir: Path) -> Path | None:
    cks = checkpoints(run_dir)
    return cks[-1] if cks else None


def save_checkpoint(run_dir: Path, step: int, state: dict[str, Any], keep: int = 2) -> Path:
    """Write step-STEP.ckpt atomically (read back whole before it gets its name), then keep
    the `keep` newest checkpoints that are whole, this one among them. A failed write (full
    disk, Ctrl-C) leaves the earlier checkpoints as they were."""
    ckdir = Path(run_dir) / "checkpoints"
    path = ckdir / f"step-{step:09d}.ckpt"
    try:
        state = {"format": FORMAT, **state, "optimizer": pack_moments(state["optimizer"])}
        atomic_write_bytes(path, lambda f: torch.save(state, f), _not_whole)
    except (OSError, RuntimeError) as e:  # torch's zip writer says "unexpected pos"
        prev = latest_checkpoint(run_dir)
        kept = f"the last good one is {prev}" if prev else "there is no earlier checkpoint"
        why = e.strerror if isinstance(e, OSError) and e.strerror else _first_sentence(e)
        raise UserError(f"{path}: could not save the checkpoint ({why}); {kept}") from None
    prune_checkpoints(run_dir, step, keep)
    return path


def prune_checkpoints(run_dir: Path, step: int, keep: int) -> list[Path]:
    """After step STEP's checkpoint was saved: remove those of steps after it (a history
    abandoned on resuming from an earlier one, whose newer files would shadow this one),
    those that are not whole (`_not_whole`) and all but the `keep` newest of the rest,
    counted by whole ones only, so that a damaged file never takes a good one's place.
    -> what was removed."""
    cks = checkpoints(run_dir)
    stale = [p for p in cks if checkpoint_step(p) > step]
    older = [p for p in cks if checkpoint_step(p) <= step]
    damaged = [p for p in older if _not_whole(p) is not None]
    whole = [p for p in older if p not in damaged]
    gone = stale + damaged + (whole[:-keep] if keep > 0 else [])
    for p in gone:
        p.unlink(missing_ok=True)
    if damaged:
        warn(f"removed {len(damaged)} damaged checkpoint(s) ({', '.join(p.name for p in damaged)})"
             f" of {run_dir}")
    return gone


def _not_whole(path: Path) -> str | None:
    """Why the file at `path` is no whole checkpoint archive (torch saves a zip archive:
    its directory must be there and every part match its CRC-32), or None."""
    try:
        with zipfile.ZipFile(path) as z:
            bad = z.testzip()
    except Exception as e:  # noqa: BLE001 - zipfile fails in many ways on a cut file
        return f"not a whole archive: {_first_sentence(e)}"
    return None if bad is None else f"{bad} fails its checksum"


class LegacyCheckpoint(UserError):
    """A checkpoint that only loads with pickle (flamenerf 0.1, or tampered with)."""


class NewerCheckpoint(UserError):
    """A checkpoint of a format this flamenerf does not read (a newer version's): never
    skipped for an older one, which a resume would then train past and overwrite."""


def load_checkpoint(path: Path) -> dict[str, Any]:
    """Load with weights_only=True; one-line errors for unreadable and pickle-needing
    files."""
    path = Path(path)
    damaged = _damaged_member(path)
    if damaged is not None:
        raise UserError(f"{path}: not a readable checkpoint (damaged: {damaged} fails its "
                        f"checksum)")
    try:
        st = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        # torch words it "Unsupported global: GLOBAL x.y" or "unsupported GLOBAL x.y whose
        # module x is blocked"
        m = re.search(r"GLOBAL ([\w.]+)", str(e))
        if m is None:
            raise UserError(f"{path}: not a readable checkpoint (UnpicklingError)") from None
        if not m.group(1).startswith(LEGACY_GLOBALS):
            # flamenerf 0.1 pickled NumPy's and Python's RNG states, nothing else: a file
            # that names os.system or builtins.eval is no run of ours to convert
            raise UserError(f"{path}: not loaded: it needs pickle for {m.group(1)}, which no "
                            "flamenerf checkpoint holds (not a flamenerf checkpoint; it may "
                            "run code when loaded: do not convert or open it)") from None
        run = path.parent.parent
        raise LegacyCheckpoint(
            f"{path}: not loaded: it needs pickle (for {m.group(1)}), which can run any code; "
            f"if you trust where this run came from, rewrite it in the safe format with "
            f"`flamenerf convert {run} --trust`") from None
    except Exception as e:  # noqa: BLE001
        raise UserError(f"{path}: not a readable checkpoint ({_first_sentence(e)})") from None
    missing = [k for k in REQUIRED if not isinstance(st, dict) or k not in st]
    if missing:
        raise UserError(f"{path}: not a readable checkpoint (no {', '.join(missing)})")
    _check_fields(st, path)
    try:
        st["optimizer"] = unpack_moments(st["optimizer"])
    except (KeyError, TypeError, ValueError, RuntimeError, IndexError) as e:
        raise UserError(f"{path}: not a readable checkpoint (optimiser state: "
                        f"{type(e).__name__})") from None
    return st


def _first_sentence(e: BaseException) -> str:
    """`e` in one short line: an OSError's reason (its message repeats the path), else the
    first sentence of its first line ("." inside a file name does not end it)."""
    if isinstance(e, OSError) and e.strerror:
        return f"{type(e).__name__}: {e.strerror}"
    line = next((ln.strip() for ln in str(e).splitlines() if ln.strip()), "")
    first = re.split(r"\.(?:\s|$)", line)[0]
    if len(first) > 160:
        first = first[:157] + "..."
    return f"{type(e).__name__}: {first}" if first else type(e).__name__


# ----------------------------------------------------------------------------- field checks

# An archive can pass its checksums and still hold the wrong things (edited, or written by
# another program): each field is checked here, so that such a file is refused like a
# damaged one (and load_latest falls back past it) instead of failing later with a traceback.


def _is_tensor(v: Any, dtype: torch.dtype, shape: tuple[int, ...]) -> bool:
    return isinstance(v, torch.Tensor) and v.dtype == dtype and tuple(v.shape) == shape


def _is_generator_state(v: Any) -> bool:
    """A CPU torch.Generator's state (also torch's global one)."""
    return _is_tensor(v, torch.uint8, tuple(torch.get_rng_state().shape))


def _is_numpy_rng(v: Any) -> bool:
    return (isinstance(v, dict) and v.get("kind") == "MT19937"
            and _is_tensor(v.get("keys"), torch.int64, (624,))
            and is_int(v.get("pos")) and 0 <= v["pos"] <= 624
            and is_int(v.get("has_gauss")) and is_number(v.get("gauss")))


def _is_python_rng(v: Any) -> bool:
    return (isinstance(v, dict) and v.get("version") == 3
            and _is_tensor(v.get("state"), torch.int64, (625,))
            and (v.get("gauss_next") is None or is_number(v.get("gauss_next"))))


# key -> (test, what it must be); "shard_generators" only where a run had several shards
_FIELDS = {
    "step": (lambda v: is_int(v) and v >= 0, "a step number (an int, at least 0)"),
    "model": (lambda v: isinstance(v, dict) and all(
        isinstance(k, str) and isinstance(t, torch.Tensor) for k, t in v.items()),
        "a dict of tensors"),
    "model_args": (lambda v: isinstance(v, dict) and all(isinstance(k, str) for k in v),
                   "a dict"),
    "optimizer": (lambda v: isinstance(v, dict) and isinstance(v.get("state"), dict)
                  and isinstance(v.get("param_groups"), list), "an optimiser state"),
    "generator": (_is_generator_state, "a random-number generator's state"),
    "torch_rng": (_is_generator_state, "a random-number generator's state"),
    "numpy_rng": (_is_numpy_rng, "NumPy's random-number state"),
    "python_rng": (_is_python_rng, "Python's random-number state"),
    "shard_generators": (lambda v: isinstance(v, list) and len(v) > 0 and all(
        _is_generator_state(g) for g in v), "a list of random-number generators' states"),
}


def _check_fields(st: dict[str, Any], path: Path) -> None:
    """A UserError (as for a damaged file) for the first field of the wrong kind."""
    fmt = st.get("format", FORMAT)  # absent in flamenerf 0.1's, which pickle refuses first
    if not is_int(fmt):
        raise UserError(f"{path}: not a readable checkpoint (format of type "
                        f"{type(fmt).__name__})")
    if fmt > FORMAT:
        raise NewerCheckpoint(f"{path}: checkpoint format {fmt} is newer than this flamenerf "
                              f"reads ({FORMAT}); update flamenerf")
    if fmt != FORMAT:
        raise UserError(f"{path}: not a readable checkpoint (format {fmt}; this flamenerf "
                        f"reads format {FORMAT}: written by another version?)")
    for key, (ok, what) in _FIELDS.items():
        if key in st and not ok(st[key]):
            raise UserError(f"{path}: not a readable checkpoint (damaged: '{key}' is not "
                            f"{what})")
    # a NaN or inf weight renders a flat grey image everywhere it is read; training stops
    # before saving one (its loss check), so such a file was damaged or written elsewhere
    for name, t in st["model"].items():
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            raise UserError(f"{path}: not a readable checkpoint (damaged: the model's "
                            f"'{name}' holds NaN or infinite values)")


def _damaged_member(path: Path) -> str | None:
    """The first part of a checkpoint (a zip archive, as torch saves) whose bytes no longer
    match their CRC-32, or None. torch.load does not check them: bytes changed in place (a
    disk or copy error) loaded silently and rendered a smeared scene. Reading the file once
    more costs ~0.1 s per 100 MB; a file that is no zip archive is left to torch.load."""
    try:
        with zipfile.ZipFile(path) as z:
            return z.testzip()
    except Exception:  # noqa: BLE001 - a directory zipfile cannot read (an unknown
        # compression method, an encryption flag: one flipped byte) is torch.load's to report
        return None


def load_latest(run_dir: Path) -> tuple[Path, dict[str, Any]] | None:
    """The newest checkpoint that loads, falling back past unreadable ones (a disk error,
    a copy cut short) with a warning that names both files. None when there is none."""
    cks = checkpoints(run_dir)
    bad: list[tuple[Path, UserError]] = []
    for p in reversed(cks):
        try:
            st = load_checkpoint(p)
        except (LegacyCheckpoint, NewerCheckpoint):
            raise
        except UserError as e:
            bad.append((p, e))
            continue
        for _, e in bad:
            warn(f"{e}; using {p.name} instead")
        return p, st
    if bad:
        raise bad[0][1]
    return None


def convert_legacy(path: Path) -> bool:
    """Rewrite a flamenerf 0.1 checkpoint in the weights_only format. Loads it with pickle:
    only for files the user trusts. Returns False when it needed no conversion."""
    try:
        load_checkpoint(path)
        return False
    except LegacyCheckpoint:
        pass
    try:
        st = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:  # noqa: BLE001 - a module the pickle names is gone, ...
        raise UserError(f"{path}: not a readable checkpoint ({_first_sentence(e)})") from None
    try:
        st["numpy_rng"], st["python_rng"] = _legacy_rng(st)
    except (TypeError, KeyError, ValueError, AttributeError, IndexError, OverflowError):
        # e.g. the states are already the safe dicts (unpacking one gave its keys, and
        # "keys".astype failed): the file needs pickle for something else
        raise UserError(f"{path}: not a flamenerf checkpoint (no random-number states of "
                        "flamenerf 0.1)") from None
    st["format"] = FORMAT
    atomic_write_bytes(Path(path), lambda f: torch.save(st, f))
    load_checkpoint(path)  # what we wrote must pass the safe loader
    return True


def _legacy_rng(st: Any) -> tuple[dict[str, Any], dict[str, Any]]:
    """flamenerf 0.1's pickled NumPy and Python RNG states (the tuples np.random.get_state
    and random.getstate return) -> the dicts of tensors and numbers that rng_states saves."""
    if not isinstance(st["numpy_rng"], tuple) or not isinstance(st["python_rng"], tuple):
        raise TypeError("not flamenerf 0.1's tuples")
    kind, keys, pos, has_gauss, gauss = st["numpy_rng"]
    version, mt, gauss_next = st["python_rng"]
    return ({"kind": str(kind), "keys": torch.from_numpy(np.asarray(keys).astype(np.int64)),
             "pos": int(pos), "has_gauss": int(has_gauss), "gauss": float(gauss)},
            {"version": int(version), "state": torch.tensor(mt, dtype=torch.int64),
             "gauss_next": gauss_next})


def load_model_state(model: torch.nn.Module, state: dict[str, Any], path: Path) -> None:
    """model.load_state_dict, with a one-line error for a checkpoint whose tensors do not fit
    this version's model (e.g. hash tables stored (F, T), as before the CPU kernel)."""
    try:
        model.load_state_dict(state)
    except (RuntimeError, TypeError, AttributeError) as e:  # TypeError: not a dict
        first = next((ln.strip() for ln in str(e).splitlines()[1:] if ln.strip()), str(e))
        if len(first) > 160:
            first = first[:157] + "..."
        raise UserError(f"{path}: checkpoint does not fit the run's model ({first}); it was "
                        "copied from another run, or written by an older flamenerf (then "
                        "train the run again)") from None
