"""Pack Python packages for a machine with no network, in parts of at most N MiB each.

    python tools/gpu_pack.py                 # -> .gpu_site/1, .gpu_site/2 and the commands
    python tools/gpu_pack.py --packages "mujoco==3.17.0 trimesh==5.2.0" --python 3.12

For a GPU machine that has Python with JAX (and scipy, flax, ...) but no network and a limit on
the files sent with each command: the rest of what the project imports there is larger than such
a limit (warp-lang's wheel alone is 149 MB).  The script

1. ``pip install --no-deps --target`` the packages (default ``PACKAGES``: what
   ``benchmarks/gpu_check.py`` needs beyond JAX) for CPython ``--python`` on manylinux x86-64,
   downloaded from the package index this machine reaches;
2. drops what no check imports (``PRUNE``: warp's examples and tests, MuJoCo Studio, test data;
   438 MiB left with warp-lang 1.19.0 and mujoco 3.17.0);
3. ``tar | xz -6`` (111 MiB) and cuts it into parts of ``--part-mib`` (two of at most 58 MiB), each in
   its own folder ``.gpu_site/K`` (git-ignored), so that each folder can be sent on its own;
4. prints one shell line per part, in order: each copies its part to /tmp/parts on the target;
   the last also joins and unpacks them into /tmp/site and runs ``benchmarks/gpu_check.py`` with
   ``PYTHONPATH=/tmp/site:$PWD`` (the target must keep /tmp between the lines).

Packing takes ~6 minutes on two cores (most of it xz).  ``--keep`` leaves the unpacked site
folder beside the parts for a look.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
# What the GPU check imports that a Python-with-JAX image lacks (pinned as pyproject.toml's
# ranges allow; warp's extra included).  websockets and importlib_resources: mujoco's and
# etils[epath]'s needs that the image lacks.
PACKAGES = ["mujoco==3.17.0", "mujoco-mjx==3.17.0", "mujoco-warp==3.17.0", "warp-lang==1.19.0",
            "trimesh==5.2.0", "coacd==1.0.14", "shapely==2.1.2", "rtree==1.4.1", "glfw",
            "pyopengl", "websockets", "importlib_resources"]
PLATFORMS = ["manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_24_x86_64",
             "manylinux_2_17_x86_64", "manylinux2014_x86_64", "manylinux_2_5_x86_64",
             "manylinux1_x86_64"]
# Folders of the installed site that no check imports, relative to it.
PRUNE = ["warp/examples", "warp/tests", "mujoco/experimental/studio", "mujoco/mjx/test_data",
         "mujoco_warp/test_data", "bin"]
OUT = ROOT / ".gpu_site"


def prune(site: Path) -> int:
    """Remove PRUNE's folders and every __pycache__ under ``site``; returns bytes left."""
    for rel in PRUNE:
        shutil.rmtree(site / rel, ignore_errors=True)
    for cache in list(site.rglob("__pycache__")):
        shutil.rmtree(cache, ignore_errors=True)
    return sum(f.stat().st_size for f in site.rglob("*") if f.is_file())


def split(archive: Path, out: Path, part_bytes: int) -> list[Path]:
    """Cut ``archive`` into folders out/1, out/2, ... each holding one part of at most
    ``part_bytes`` (``<name>.part-K``); returns the part files.  ``cat`` of the parts in order
    gives the archive back."""
    if part_bytes < 1:
        raise ValueError("part_bytes must be >= 1")
    shutil.rmtree(out, ignore_errors=True)
    parts = []
    with archive.open("rb") as src:
        k = 1
        while chunk := src.read(part_bytes):
            folder = out / str(k)
            folder.mkdir(parents=True)
            part = folder / f"{archive.name}.part-{k:02d}"
            part.write_bytes(chunk)
            parts.append(part)
            k += 1
    return parts


def commands(parts: list[Path], check_args: str) -> list[tuple[str, str]]:
    """(folder to send, shell line to run beside it) for each part, in order."""
    out = []
    for k, part in enumerate(parts, 1):
        folder = str(part.parent.relative_to(ROOT))
        stash = f"mkdir -p /tmp/parts && cp {folder}/* /tmp/parts/"
        if k < len(parts):
            out.append((folder, stash + " && ls -la /tmp/parts"))
        else:
            out.append((folder, stash + " && cat /tmp/parts/*.part-* | xz -dc -T0 | tar xf - -C /tmp && "
                        "export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 && "
                        f"python3 benchmarks/gpu_check.py {check_args} --out $OUT/gpu_check.json "
                        "2>&1 | tee $OUT/gpu_check.log"))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--part-mib", type=int, default=58,
                   help="MiB per part (default 58: under a 64 MiB limit with the repository beside it)")
    p.add_argument("--packages", default=None,
                   help="space-separated requirements (default: what gpu_check.py needs beyond JAX)")
    p.add_argument("--python", default="3.12", help="the target's Python version (default 3.12)")
    p.add_argument("--check-args", default="",
                   help="arguments for gpu_check.py in the last line (default: none, its defaults)")
    p.add_argument("--keep", action="store_true", help="keep the unpacked site folder (.gpu_site/site)")
    args = p.parse_args(argv)
    if args.part_mib < 1:
        p.error("--part-mib must be >= 1")
    packages = PACKAGES if args.packages is None else args.packages.split()
    if not packages:
        p.error("--packages names no package")
    if not shutil.which("xz") or not shutil.which("tar"):
        p.error("needs tar and xz on this machine")
    with tempfile.TemporaryDirectory(prefix="f2f-gpu-pack-") as tmp:
        site = Path(tmp) / "site"
        pip = [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--only-binary=:all:",
               "--python-version", args.python, "--implementation", "cp",
               *[f"--platform={x}" for x in PLATFORMS], "--target", str(site), *packages]
        print(f"installing for CPython {args.python}, manylinux x86-64:", " ".join(packages), flush=True)
        subprocess.run(pip, check=True)
        left = prune(site)
        print(f"pruned: {left / 2**20:.0f} MiB left; compressing (xz -6, minutes)", flush=True)
        archive = Path(tmp) / "site.tar.xz"
        with archive.open("wb") as f:
            tar = subprocess.Popen(["tar", "cf", "-", "-C", tmp, "site"], stdout=subprocess.PIPE)
            subprocess.run(["xz", "-T0", "-6"], stdin=tar.stdout, stdout=f, check=True)
            if tar.wait():
                raise RuntimeError("tar failed")
        size = archive.stat().st_size
        parts = split(archive, OUT, args.part_mib * 2**20)
        if args.keep:
            shutil.copytree(site, OUT / "site")
    print(f"{size / 2**20:.0f} MiB in {len(parts)} parts under {OUT}\n")
    for k, (folder, command) in enumerate(commands(parts, args.check_args), 1):
        print(f"{k}. send {folder}/, then run: {command}")
    print("\nIn order, on one machine that keeps /tmp between them.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
