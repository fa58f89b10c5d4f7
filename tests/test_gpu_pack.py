"""tools/gpu_pack.py: the parts join back into the archive, and the lines it prints stash
every part before the last one unpacks them."""

import importlib

import pytest

pack = importlib.import_module("tools.gpu_pack")


def test_parts_are_small_enough_and_join_back_into_the_archive(tmp_path):
    archive = tmp_path / "site.tar.xz"
    data = bytes(range(256)) * 41 + b"tail"  # 10,500 bytes: three parts of 4,000 at most
    archive.write_bytes(data)
    parts = pack.split(archive, tmp_path / "out", 4000)
    assert [p.parent.name for p in parts] == ["1", "2", "3"]
    assert all(p.stat().st_size <= 4000 for p in parts)
    assert b"".join(p.read_bytes() for p in sorted(parts)) == data
    # a second packing replaces the first's parts instead of mixing with them
    archive.write_bytes(data[:100])
    again = pack.split(archive, tmp_path / "out", 4000)
    assert len(again) == 1 and sorted((tmp_path / "out").iterdir()) == [again[0].parent]
    with pytest.raises(ValueError):
        pack.split(archive, tmp_path / "out", 0)


def test_prune_drops_what_no_check_imports_and_keeps_the_rest(tmp_path):
    site = tmp_path / "site"
    for rel in ("warp/examples/assets/bunny.usd", "warp/tests/test_apic.py",
                "warp/__pycache__/context.cpython-312.pyc", "warp/bin/warp.so", "warp/_src/context.py",
                "mujoco/experimental/studio/app.so", "mujoco/mjx/_src/io.py"):
        (site / rel).parent.mkdir(parents=True, exist_ok=True)
        (site / rel).write_bytes(b"x" * 10)
    left = pack.prune(site)
    kept = sorted(str(f.relative_to(site)) for f in site.rglob("*") if f.is_file())
    assert kept == ["mujoco/mjx/_src/io.py", "warp/_src/context.py", "warp/bin/warp.so"]
    assert left == 30


def test_every_line_but_the_last_only_stashes_its_part(tmp_path, monkeypatch):
    monkeypatch.setattr(pack, "ROOT", tmp_path)
    parts = [tmp_path / ".gpu_site" / str(k) / f"site.tar.xz.part-0{k}" for k in (1, 2)]
    lines = pack.commands(parts, "--only agreement")
    assert [folder for folder, _ in lines] == [".gpu_site/1", ".gpu_site/2"]
    assert "gpu_check" not in lines[0][1] and "cp .gpu_site/1/*" in lines[0][1]
    last = lines[1][1]
    assert last.index("cp .gpu_site/2/*") < last.index("xz -dc") < last.index("gpu_check.py --only agreement")
