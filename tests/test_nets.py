"""Flax networks: shapes, parameter counts, layouts, frozen parts, and a tiny AE that learns."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from scipy import ndimage

from f2f_jax import config
from f2f_jax.errors import VolumeError
from f2f_jax.nets import (
    FingerGenerator,
    FitnessNet,
    Generator,
    ShapeAutoEncoder,
    ShapeDecoder,
    ShapeEncoder,
    count_params,
    fitness_input,
    summarize,
)
from f2f_jax.nets import __main__ as nets_cli
from f2f_jax.nets.shape import VolumeConv, VolumeConvTranspose, _fold_depth_conv, conv3d
from f2f_jax.train.losses import vae_loss

R = 40


@pytest.fixture(scope="module")
def tiny_net():
    return config.tiny().net


@pytest.fixture(scope="module")
def volumes():
    """[2, 40, 40, 40] float32 TSDF-like volumes in [-1, 1]."""
    return jax.random.uniform(jax.random.key(0), (2, R, R, R), minval=-1.0, maxval=1.0)


def _sphere_tsdfs(n: int, seed: int) -> np.ndarray:
    """[n, 40, 40, 40] TSDFs (truncation 5 voxels) of random spheres."""
    rng = np.random.default_rng(seed)
    g = np.arange(R) + 0.5
    x, y, z = np.meshgrid(g, g, g, indexing="ij")
    out = []
    for _ in range(n):
        c = rng.uniform(14, 26, 3)
        r = rng.uniform(6, 12)
        d = np.sqrt((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2) - r
        out.append(np.clip(d / 5.0, -1, 1))
    return np.stack(out).astype(np.float32)


# ---------------------------------------------------------------- shapes and parameter counts


def test_tiny_output_shapes(tiny_net):
    rows = {row["name"]: row for row in summarize(tiny_net, batch=3)}
    lat = tiny_net.latent_dim
    assert rows["ShapeEncoder"]["outputs"] == ((3, lat), (3, lat))
    assert rows["ShapeDecoder"]["outputs"] == (3, R, R, R)
    assert rows["Generator"]["outputs"] == ((3, lat), (3, lat))
    assert rows["ShapeAutoEncoder"]["outputs"] == ((3, R, R, R), (3, lat), (3, lat))
    assert rows["FingerGenerator"]["outputs"] == ((3, R, R, R), (3, R, R, R))
    assert rows["FitnessNet"]["outputs"] == (3, 11)
    # the composite nets are exactly their parts
    assert rows["ShapeAutoEncoder"]["params"] == (rows["ShapeEncoder"]["params"]
                                                  + rows["ShapeDecoder"]["params"])
    assert rows["FingerGenerator"]["params"] == (rows["ShapeAutoEncoder"]["params"]
                                                 + rows["Generator"]["params"])


def _conv_bn(c_in, c_out, k=3):
    return k ** 3 * c_in * c_out + 2 * c_out  # bias-free conv + BatchNorm scale and shift


def _dense_bn(n_in, n_out):
    return n_in * n_out + 2 * n_out


def expected_counts(cfg) -> dict[str, int]:
    """Parameter counts derived from the layer lists (paper appendix B.2), independently."""
    lat = cfg.latent_dim
    enc, c, size = 0, 1, R
    for width, stride in zip(cfg.encoder_channels, cfg.encoder_strides):
        enc += _conv_bn(c, width)
        c, size = width, (size - 3) // stride + 1
    enc += 2 * (c * size ** 3 * lat + lat)  # mu and logvar heads, with bias
    dec, n = 0, lat
    for width in cfg.decoder_fc:
        dec += _dense_bn(n, width)
        n = width
    c = cfg.decoder_fc[-1] // cfg.decoder_seed_size ** 3
    for width in cfg.decoder_channels[:-1]:
        dec += _conv_bn(c, width)
        c = width
    dec += 27 * c * cfg.decoder_channels[-1] + cfg.decoder_channels[-1]  # output layer: bias, no BN
    gen, n = 0, lat
    for width in cfg.generator_fc:
        gen += _dense_bn(n, width)
        n = width
    gen += n * 2 * lat + 2 * lat
    fit, c = 0, 1
    for stage, (width, blocks) in enumerate(zip(cfg.fitness_channels, cfg.fitness_blocks)):
        fit += _conv_bn(c, width, 5 if stage == 0 else 3)
        fit += blocks * 2 * _conv_bn(width, width)
        c = width
    fit += _conv_bn(c, c)
    n = c  # 1 x 1 x 1 x channels after seven stride-2 convolutions of 120 x 40 x 40
    for width in cfg.fitness_fc:
        fit += _dense_bn(n, width)
        n = width
    fit += n * 11 + 11
    return {"ShapeEncoder": enc, "ShapeDecoder": dec, "Generator": gen, "FitnessNet": fit}


@pytest.mark.parametrize("name", ["tiny", "default"])
def test_param_counts_match_layer_lists(name):
    cfg = config.get(name).net
    rows = {row["name"]: row["params"] for row in summarize(cfg)}
    for module, count in expected_counts(cfg).items():
        assert rows[module] == count, module


def test_default_is_paper_size():
    rows = {row["name"]: row for row in summarize(config.default().net)}
    # paper: 686-d latent, generator FC(2096)-FC(4096)-FC(1372), fitness ends in 1024 features
    assert rows["ShapeEncoder"]["outputs"] == ((2, 686), (2, 686))
    assert rows["Generator"]["params"] == 686 * 2096 + 2 * 2096 + 2096 * 4096 + 2 * 4096 + 4096 * 1372 + 1372
    assert 100e6 < rows["FitnessNet"]["params"] < 150e6


def test_summary_cli_prints_counts(capsys, tiny_net):
    assert nets_cli.main(["--summary", "--config", "tiny"]) == 0
    out = capsys.readouterr().out
    rows = {row["name"]: row["params"] for row in summarize(tiny_net)}
    for name in ("ShapeEncoder", "ShapeDecoder", "Generator", "FitnessNet", "FingerGenerator/embedding"):
        line = next(ln for ln in out.splitlines() if ln.startswith(name + " "))
        assert f"{rows[name]:,}" in line
    total = rows["ShapeEncoder"] + rows["ShapeDecoder"] + rows["Generator"] + rows["FitnessNet"]
    assert f"{total:,}" in out.splitlines()[-1]


# ---------------------------------------------------------------- running the tiny nets


def test_tiny_nets_jit_and_run(tiny_net, volumes):
    lat = tiny_net.latent_dim
    key = jax.random.key(1)
    cases = [
        (ShapeEncoder(tiny_net), volumes),
        (ShapeDecoder(tiny_net), jnp.tanh(jax.random.normal(key, (2, lat)))),
        (Generator(tiny_net), jnp.tanh(jax.random.normal(key, (2, lat)))),
        (FitnessNet(tiny_net), fitness_input(volumes, volumes, volumes)),
    ]
    for module, x in cases:
        variables = module.init(key, x, train=False)
        train_fn = jax.jit(lambda v, x, m=module: m.apply(v, x, train=True, mutable=["batch_stats"]))
        eval_fn = jax.jit(lambda v, x, m=module: m.apply(v, x, train=False))
        out, updates = train_fn(variables, x)
        for leaf in jax.tree.leaves(out) + jax.tree.leaves(eval_fn(variables, x)):
            assert bool(jnp.all(jnp.isfinite(leaf))), type(module).__name__
        # training mode moves the running statistics; evaluation mode reads them
        moved = jax.tree.map(lambda a, b: bool(jnp.any(a != b)), updates["batch_stats"],
                             variables["batch_stats"])
        assert any(jax.tree.leaves(moved)), type(module).__name__
    mu, logvar = ShapeEncoder(tiny_net).apply(
        ShapeEncoder(tiny_net).init(key, volumes, train=False), volumes, train=False)
    assert float(jnp.max(jnp.abs(mu))) < 1.0  # tanh: the paper's [-1, 1] latent


def test_autoencoder_sampling(tiny_net, volumes):
    ae = ShapeAutoEncoder(tiny_net)
    variables = ae.init(jax.random.key(0), volumes, train=False)
    with pytest.raises(ValueError, match="PRNG key"):
        ae.apply(variables, volumes, train=True, mutable=["batch_stats"])

    def run(key):
        return ae.apply(variables, volumes, train=True, key=key, mutable=["batch_stats"])[0][0]

    a, b, a2 = run(jax.random.key(1)), run(jax.random.key(2)), run(jax.random.key(1))
    assert bool(jnp.all(a == a2)) and bool(jnp.any(a != b))
    recon, mu, _ = ae.apply(variables, volumes, train=False)
    direct = ae.apply(variables, mu, train=False, method=ShapeAutoEncoder.decode)
    np.testing.assert_allclose(recon, direct, atol=1e-6)  # evaluation decodes the mean
    assert recon.shape == (2, R, R, R) and float(jnp.max(jnp.abs(recon))) <= 1.0


def test_wrong_volume_shapes_are_refused(tiny_net):
    enc = ShapeEncoder(tiny_net)
    with pytest.raises(VolumeError, match=r"\[B, 40, 40, 40\]"):
        enc.init(jax.random.key(0), jnp.zeros((40, 40, 40)), train=False)
    with pytest.raises(VolumeError, match="FitnessNet"):
        FitnessNet(tiny_net).init(jax.random.key(0), jnp.zeros((2, 40, 40, 40)), train=False)
    with pytest.raises(VolumeError, match="right finger"):
        fitness_input(jnp.zeros((40, 40, 40)), jnp.zeros((40, 40, 40)), jnp.zeros((40, 40)))


def test_finger_generator_parts_are_separable_and_frozen(tiny_net, volumes):
    fg = FingerGenerator(tiny_net)
    variables = fg.init(jax.random.key(0), volumes, train=False)
    assert set(variables["params"]) == {"encoder", "embedding", "decoder"}

    # pretrained auto-encoder weights move over unchanged
    ae = ShapeAutoEncoder(tiny_net)
    ae_vars = ae.init(jax.random.key(5), volumes, train=False)
    params = {**variables["params"], "encoder": ae_vars["params"]["encoder"],
              "decoder": ae_vars["params"]["decoder"]}
    stats = {**variables["batch_stats"], "encoder": ae_vars["batch_stats"]["encoder"],
             "decoder": ae_vars["batch_stats"]["decoder"]}
    mu_ae, _ = ae.apply(ae_vars, volumes, method=ShapeAutoEncoder.encode)
    mu_fg = fg.apply({"params": params, "batch_stats": stats}, volumes,
                     method=FingerGenerator.object_latent)
    np.testing.assert_allclose(mu_ae, mu_fg, atol=1e-6)

    def loss(p):
        (left, right), upd = fg.apply({"params": p, "batch_stats": stats}, volumes, train=True,
                                      mutable=["batch_stats"])
        return jnp.mean(left) - jnp.mean(right), upd

    grads, upd = jax.grad(loss, has_aux=True)(params)
    norm = {k: sum(float(jnp.sum(jnp.square(g))) for g in jax.tree.leaves(v)) for k, v in grads.items()}
    assert norm["encoder"] == 0.0  # cut from the graph: no backward pass through the encoder
    assert norm["embedding"] > 0.0 and norm["decoder"] > 0.0
    # only the embedding's BatchNorm statistics move in training mode
    for part in ("encoder", "decoder"):
        same = jax.tree.map(lambda a, b: bool(jnp.all(a == b)), upd["batch_stats"][part], stats[part])
        assert all(jax.tree.leaves(same)), part
    moved = jax.tree.map(lambda a, b: bool(jnp.any(a != b)), upd["batch_stats"]["embedding"],
                         stats["embedding"])
    assert any(jax.tree.leaves(moved))

    # latents decoded by the frozen decoder are the fingers
    lz, rz = fg.apply({"params": params, "batch_stats": stats}, volumes, train=False,
                      method=FingerGenerator.latents)
    left, right = fg.apply({"params": params, "batch_stats": stats}, volumes, train=False)
    dec = ShapeDecoder(tiny_net)
    dvars = {"params": params["decoder"], "batch_stats": stats["decoder"]}
    np.testing.assert_allclose(left, dec.apply(dvars, lz, train=False), atol=1e-5)
    np.testing.assert_allclose(right, dec.apply(dvars, rz, train=False), atol=1e-5)


# ---------------------------------------------------------------- convolution paths


@pytest.mark.parametrize("kernel,stride,padding", [(3, 1, 0), (3, 2, 1), (5, 2, 2), (3, 1, 2)])
def test_fold_depth_conv_matches_3d_conv(kernel, stride, padding):
    x = jax.random.normal(jax.random.key(0), (2, 11, 9, 10, 3))
    w = jax.random.normal(jax.random.key(1), (kernel,) * 3 + (3, 4))
    ref = jax.lax.conv_general_dilated(x, w, (stride,) * 3, [(padding, padding)] * 3,
                                       dimension_numbers=("NDHWC", "DHWIO", "NDHWC"))
    xp = jnp.pad(x, ((0, 0),) + ((padding, padding),) * 3 + ((0, 0),))
    np.testing.assert_allclose(_fold_depth_conv(xp, w, stride), ref, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(conv3d(x, w, stride, padding), ref, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("stride", [1, 2, 3])
def test_transpose_conv_matches_lax(stride):
    x = jax.random.normal(jax.random.key(0), (2, 4, 5, 3, 3))
    m = VolumeConvTranspose(2, 3, stride)
    variables = m.init(jax.random.key(1), x)
    ref = jax.lax.conv_transpose(x, variables["params"]["kernel"], (stride,) * 3, "VALID",
                                 dimension_numbers=("NDHWC", "DHWIO", "NDHWC"))
    out = m.apply(variables, x)
    assert out.shape == (2, 3 * stride + 3, 4 * stride + 3, 2 * stride + 3, 2)  # (n - 1) s + k
    np.testing.assert_allclose(out, ref, rtol=1e-4, atol=1e-4)


def test_volume_conv_bias_and_shape():
    x = jnp.ones((1, 8, 8, 8, 2))
    m = VolumeConv(3, 3, 2, 1, use_bias=True)
    variables = m.init(jax.random.key(0), x)
    assert variables["params"]["kernel"].shape == (3, 3, 3, 2, 3)
    assert m.apply(variables, x).shape == (1, 4, 4, 4, 3)


# ---------------------------------------------------------------- fitness-net layout


def test_fitness_input_index_layout():
    left = np.zeros((R, R, R), np.float32)
    right = np.zeros((R, R, R), np.float32)
    obj = np.zeros((R, R, R), np.float32)
    u, v, w = 3, 7, 11  # an asymmetric marker: every index different
    left[u, v, w] = 1.0
    right[u, v, w] = 2.0
    obj[5, 6, 9] = 3.0
    out = np.asarray(fitness_input(obj, left, right))
    assert out.shape == (3 * R, R, R)
    # left: w -> +x, u -> +y, v -> +z, mount (w = 0) at x = 0
    assert out[w, u, v] == 1.0
    # object in the middle block, unchanged
    assert out[R + 5, 6, 9] == 3.0
    # right: w -> -x, u -> -y, v -> +z, mount (w = 0) at x = 119
    assert out[3 * R - 1 - w, R - 1 - u, v] == 2.0
    assert np.count_nonzero(out) == 3
    # batched input gives the same layout per item
    batched = np.asarray(fitness_input(obj[None], left[None], right[None]))
    np.testing.assert_array_equal(batched[0], out)


def test_fitness_input_imprint_fingers_face_the_object():
    """Imprint fingers (geometry) land where they cage the object: a contract across modules."""
    from f2f_jax.geometry import imprint_fingers

    occ = np.zeros((R, R, R), bool)
    occ[8:32, 22:36, 1:14] = True  # a wide low slab on the +y side
    occ[14:26, 26:34, 14:30] = True  # a tower on it, also +y
    sdf = ndimage.distance_transform_edt(~occ) - ndimage.distance_transform_edt(occ)
    obj = np.clip(sdf / 5.0, -1, 1).astype(np.float32)
    left, right = imprint_fingers(obj)
    vol = np.asarray(fitness_input(obj, left, right))
    profile = (vol[R: 2 * R] < 0).any(axis=0)  # object's [y, z] silhouette seen along x
    for name, block, mount_x in (("left", vol[:R], 0), ("right", vol[2 * R:], R - 1)):
        solid = block < 0
        assert solid[mount_x].all(), f"{name} finger's mount plane is not solid"
        depth = solid.sum(axis=0).astype(float)  # finger thickness along x per [y, z]
        # the imprint is recessed exactly behind the object's silhouette
        assert depth[profile].mean() < depth[~profile].mean() - 5, name
        assert np.corrcoef(depth.ravel(), profile.ravel())[0, 1] < -0.5, name


# ---------------------------------------------------------------- learning


def test_tiny_autoencoder_overfits_four_shapes(tiny_net):
    shapes = jnp.asarray(_sphere_tsdfs(4, seed=0))
    ae = ShapeAutoEncoder(tiny_net)
    variables = ae.init(jax.random.key(0), shapes, train=False)
    opt = optax.adam(1e-2)
    state = (variables["params"], variables["batch_stats"], opt.init(variables["params"]))

    @jax.jit
    def step(state, key):
        params, stats, opt_state = state

        def loss_fn(p):
            (recon, mu, logvar), upd = ae.apply({"params": p, "batch_stats": stats}, shapes,
                                                train=True, key=key, mutable=["batch_stats"])
            return vae_loss(recon, shapes, mu, logvar, kl_weight=1e-3), upd["batch_stats"]

        (loss, stats), grads = jax.value_and_grad(loss_fn, has_aux=True)(params)
        updates, opt_state = opt.update(grads, opt_state, params)
        return (optax.apply_updates(params, updates), stats, opt_state), loss

    keys = jax.random.split(jax.random.key(1), 25)
    losses = []
    for key in keys:
        state, loss = step(state, key)
        losses.append(loss)
    losses = np.asarray(jax.device_get(losses))
    assert np.all(np.isfinite(losses))
    assert losses[-3:].mean() < 0.5 * losses[:3].mean(), losses
