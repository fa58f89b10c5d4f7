import numpy as np
import pytest

from f2f_jax.dataset.store import GraspStore


def _rows(n, seed):
    rng = np.random.default_rng(seed)
    vols = [rng.uniform(-1, 1, (n, 40, 40, 40)).astype(np.float32) for _ in range(3)]
    return vols, rng.integers(0, 2, (n, 11))


def test_append_and_read_back(tmp_path):
    store = GraspStore(tmp_path / "store")
    assert len(store) == 0 and store.done_keys() == set()
    (o, l, r), out = _rows(5, 0)
    store.append(o, l, r, out, kind="imprint", names=[f"o{i}" for i in range(5)], keys=["a", "b"])
    (o2, l2, r2), out2 = _rows(3, 1)
    store.append(o2, l2, r2, out2, kind=["cut"] * 3, keys=["c"], cycle=2)
    assert len(store) == 8 and store.done_keys() == {"a", "b", "c"}
    data = store.read(("object", "left", "outcome", "kind", "cycle"))
    assert np.allclose(data["object"][:5], o, atol=1e-3)  # float16 on disk
    assert np.allclose(data["left"][5:], l2, atol=1e-3)
    assert np.array_equal(data["outcome"], np.concatenate([out, out2]))
    assert list(data["kind"]) == ["imprint"] * 5 + ["cut"] * 3
    assert list(data["cycle"]) == [-1] * 5 + [2] * 3
    part = store.read(("outcome",), start=4, stop=6)
    assert np.array_equal(part["outcome"], np.concatenate([out, out2])[4:6])
    # a fresh reader sees the same
    assert len(GraspStore(tmp_path / "store")) == 8


def test_half_written_chunk_is_invisible(tmp_path):
    store = GraspStore(tmp_path)
    (o, l, r), out = _rows(2, 0)
    store.append(o, l, r, out, kind="wsg50", keys=["x"])
    # What a writer killed mid-chunk leaves behind: a temporary file, never a chunk name.
    (tmp_path / ".chunk-000001.h5.999.tmp").write_bytes(b"\x89HDF garbage")
    fresh = GraspStore(tmp_path)
    assert len(fresh) == 2 and fresh.done_keys() == {"x"}
    assert fresh.clean_temporary() == 1
    fresh.append(o, l, r, out, kind="wsg50", keys=["y"])
    assert [c.index for c in fresh.chunks()] == [0, 1]


def test_bad_append_is_refused(tmp_path):
    store = GraspStore(tmp_path)
    (o, l, r), out = _rows(2, 0)
    with pytest.raises(ValueError, match="must be"):
        store.append(o, l[:1], r, out, kind="imprint")
    with pytest.raises(ValueError, match="one entry per row"):
        store.append(o, l, r, out, kind=["imprint"])
    assert len(store) == 0
