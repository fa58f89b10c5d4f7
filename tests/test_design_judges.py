"""benchmarks/design_judges.py ``--pool``: the outcomes of several finished ``--out`` folders, their
objects put together, for the designs every folder holds under both judges."""

import importlib
import json

import numpy as np
import pytest

judges = importlib.import_module("benchmarks.design_judges")


def _folder(path, outcomes: dict[str, np.ndarray]):
    """A finished ``--out`` folder: judges.json and one npz per (judge, design); the PyBullet peer
    sees every outcome with the last trial flipped."""
    path.mkdir()
    summary = {"judges": {}}
    for j in judges.JUDGES:
        for name, o in outcomes.items():
            o = o.copy()
            if j == "pybullet":
                o[:, -1] ^= 1
            np.savez_compressed(path / f"judge-{j}-{name.replace(' ', '_')}.npz", outcome=o)
            summary["judges"].setdefault(j, {})[name] = {"trials": float(o.sum(1).mean())}
    (path / "judges.json").write_text(json.dumps(summary))
    return path


def test_pool_puts_the_folders_objects_together_for_the_designs_all_hold(tmp_path, capsys):
    rng = np.random.default_rng(0)
    imp1, imp2 = (rng.integers(0, 2, (n, 11)).astype(np.uint8) for n in (5, 7))
    a1, a2 = imp1.copy(), imp2.copy()
    a1[:2, 1:4] = 1  # the net gains on some objects of either folder
    a2[:3, 5:8] = 1
    b1 = 1 - imp1
    f1 = _folder(tmp_path / "one", {"Imprint": imp1, "teacher": a1, "other": b1})
    f2 = _folder(tmp_path / "two", {"Imprint": imp2, "teacher": a2})  # "other" was not judged here
    out = judges.pool_main([str(f1), str(f2)])
    for j in judges.JUDGES:
        assert set(out["judges"][j]) == {"Imprint", "teacher"}  # only what both folders hold
        imp, a = np.concatenate([imp1, imp2]), np.concatenate([a1, a2])
        if j == "pybullet":
            imp[:, -1] ^= 1
            a[:, -1] ^= 1
        row = out["judges"][j]["teacher"]
        assert row["trials"] == pytest.approx(a.sum(1).mean())
        assert row["minus_imprint"]["diff"] == pytest.approx((a.sum(1) - imp.sum(1)).mean())
        assert row["minus_imprint"]["diff"] > 0  # the gains above, on 5 of the 12 objects
        assert row["minus_imprint"]["better"] == int((a.sum(1) > imp.sum(1)).sum())
    printed = capsys.readouterr().out
    assert "12 objects" in printed and "(5 objects)" in printed and "(7 objects)" in printed


def test_pool_refuses_one_folder_or_an_unfinished_one(tmp_path):
    o = np.ones((3, 11), np.uint8)
    done = _folder(tmp_path / "done", {"Imprint": o})
    with pytest.raises(SystemExit, match="two or more"):
        judges.pool_main([str(done)])
    (tmp_path / "unfinished").mkdir()
    with pytest.raises(SystemExit, match="unfinished"):
        judges.main(["--pool", str(done), str(tmp_path / "unfinished")])
