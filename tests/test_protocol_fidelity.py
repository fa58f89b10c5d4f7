"""benchmarks/protocol_fidelity.py end to end on the smallest set: our protocol and the PyBullet
original on the same triples, the report's figures consistent with the outcomes."""

import importlib
import json

import pytest

pytest.importorskip("pybullet")
fidelity = importlib.import_module("benchmarks.protocol_fidelity")


@pytest.mark.slow
def test_fidelity_report_on_one_object(tmp_path, capsys, monkeypatch):
    out, png = tmp_path / "fidelity.json", tmp_path / "both.png"
    # one ablation a side: a friction that lets our flat pads lift the bottle, and the original's
    # self-collision, which leaves the peer's imprint grasp of it as it was
    monkeypatch.setattr(fidelity, "ABLATIONS", (
        ("ours", "friction 1.0", dict(finger_friction=1.0)),
        ("pybullet", "self-collision", dict(self_collision=True))))
    assert fidelity.main(["--n-objects", "1", "--config", "tiny", "--kinds", "imprint", "flat",
                          "--workers", "2", "--json", str(out), "--render", str(png),
                          "--ablations"]) == 0
    res = json.loads(out.read_text())
    assert png.exists() == bool(res["differing"])
    base, ours, theirs = res["ablations"]
    assert base["moved"] == 0.0 and [ours["side"], theirs["side"]] == ["ours", "pybullet"]
    assert ours["rates"]["flat"]["fast"]["grasp"] == 1.0  # mu 1.0: flat pads hold 2 N > 0.49 N
    assert ours["rates"]["flat"]["pybullet"]["grasp"] == 0.0  # the other side as it was
    assert ours["moved"] > 0
    assert theirs["rates"]["imprint"]["pybullet"]["grasp"] == 1.0
    assert res["n"] == 2 and res["kinds"] == ["imprint", "flat"]
    assert set(res["agreement"]) == {"fast", "reference"}
    for sim in ("fast", "reference", "pybullet"):
        # builtin object 0 (a bottle) held by its imprint in every simulator; flat pads slip at mu 0.2
        assert res["rates"]["imprint"][sim]["grasp"] == 1.0
        assert res["rates"]["flat"][sim]["grasp"] == 0.0
    for stats in res["agreement"].values():
        assert stats["agreement_per_kind"]["flat"] == 1.0  # all zeros on both sides
        n_diff = sum(1 for d in res["differing"] if d["fast"] != d["pybullet"])
        assert (stats["agreement_vectors"] == 1.0) == (n_diff == 0)
    assert [t["kind"] for t in res["triples"]] == ["imprint", "flat"]
    assert all(len(res["outcomes"][s]) == 2 and len(res["outcomes"][s][0]) == 11
               for s in ("fast", "reference", "pybullet"))
    assert res["outcomes"]["pybullet"][1] == "0" * 11  # the flat pads: nothing held
    assert "agreement with the PyBullet original" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        fidelity.main(["--n-objects", "0"])
