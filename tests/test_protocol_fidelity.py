"""research/protocol_fidelity.py end to end on the smallest set: our protocol and the PyBullet
original on the same triples, the report's figures consistent with the outcomes."""

import importlib
import json

import numpy as np
import pytest

pytest.importorskip("pybullet")
fidelity = importlib.import_module("research.protocol_fidelity")


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


def test_every_ablation_names_fields_that_exist_on_its_side():
    """Our side's keys are SimConfig fields; the peer's are OriginalProtocol fields, or "sim."
    and a SimConfig field (the shared settings).  A name lookup instead of the prefix once sent
    the peer's "finger-object friction 0.4" to the finger links' friction, which Bullet
    multiplies by the object's 0.2: the row lowered the friction it meant to raise."""
    import dataclasses

    from f2f_jax.bench import pybullet_runs as peer
    from f2f_jax.config import SimConfig

    proto = {f.name for f in dataclasses.fields(peer.OriginalProtocol)}
    sim_fields = {f.name for f in dataclasses.fields(SimConfig)}
    for side, label, changes in fidelity.ABLATIONS:
        allowed = sim_fields if side == "ours" else proto | {peer.SIM_PREFIX + f for f in sim_fields}
        assert side in ("ours", "pybullet") and set(changes) <= allowed, (side, label, changes)
    friction = [c for s, label, c in fidelity.ABLATIONS if s == "pybullet" and "friction 0.4" in label]
    assert friction == [{"sim.finger_friction": 0.4}]


def test_a_peer_ablation_changes_the_protocol_or_the_shared_config_by_its_prefix(monkeypatch):
    from f2f_jax import config
    from f2f_jax.bench import pybullet_runs as peer

    seen = {}

    def capture(objects, lefts, rights, *, cfg, protocol):
        seen.update(cfg=cfg, protocol=protocol)
        return np.zeros((0, 11), np.uint8), {"steps": 0}

    monkeypatch.setattr(peer, "evaluate_original", capture)
    peer.peer_chunk(([], [], [], config.default(), {"sim.finger_friction": 0.4, "substeps": 4}))
    assert seen["cfg"].sim.finger_friction == 0.4  # the object's lateral friction in Bullet
    assert seen["protocol"].substeps == 4
    assert seen["protocol"].finger_lateral_friction == peer.PROTOCOL.finger_lateral_friction
