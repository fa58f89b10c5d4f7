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
from f2f_jax.nets.fitness import STEM_KERNEL
from f2f_jax.nets.shape import VolumeConv, VolumeConvTranspose, _fold_depth_conv, conv3d
from f2f_jax.train.losses import vae_loss

R = 40


def init_key(seed: int) -> jax.Array:
    """An init key whose generator compiles fast on the CPU.

    Flax draws every parameter from its own folded key; with the default threefry generator that
    is one large hash circuit per parameter, and XLA's CPU compiler spends 10-15 s on a tiny net's
    ``init``.  The 'rbg' generator compiles in 1-3 s.
    """
    return jax.random.key(seed, impl="rbg")


def jit_init(module, seed, *args):
    return jax.jit(lambda k: module.init(k, *args, train=False))(init_key(seed))


@pytest.fixture(scope="module")
def tiny_net():
    return config.tiny().net


@pytest.fixture(scope="module")
def ae_variables(tiny_net):
    """Initialised tiny ShapeAutoEncoder variables, shared by the tests that need them."""
    return jit_init(ShapeAutoEncoder(tiny_net), 5, jnp.zeros((2, R, R, R)))


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
    kernels = cfg.decoder_kernels or (3,) * len(cfg.decoder_channels)
    for width, k in zip(cfg.decoder_channels[:-1], kernels):
        dec += _conv_bn(c, width, k)
        c = width
    # output layer: bias, no BN
    dec += kernels[-1] ** 3 * c * cfg.decoder_channels[-1] + cfg.decoder_channels[-1]
    gen, n = 0, lat
    for width in cfg.generator_fc:
        gen += _dense_bn(n, width)
        n = width
    gen += n * 2 * lat + 2 * lat
    fit, c, dims = 0, 1, np.array([3 * R, R, R])
    for stage, (width, blocks) in enumerate(zip(cfg.fitness_channels, cfg.fitness_blocks)):
        fit += _conv_bn(c, width, STEM_KERNEL if stage == 0 else 3)
        fit += blocks * 2 * _conv_bn(width, width)
        c, dims = width, (dims - 1) // 2 + 1  # stride 2, "same" padding
    fit += _conv_bn(c, c)
    dims = (dims - 1) // 2 + 1
    n = c * int(np.prod(dims))  # the paper's sizes: 1 x 1 x 1 x 1024 after seven convolutions
    for width in cfg.fitness_fc:
        fit += _dense_bn(n, width)
        n = width
    fit += n * 11 + 11
    return {"ShapeEncoder": enc, "ShapeDecoder": dec, "Generator": gen, "FitnessNet": fit}


@pytest.mark.parametrize("name", ["tiny", "default", "paper"])
def test_param_counts_match_layer_lists(name):
    cfg = config.get(name).net
    rows = {row["name"]: row["params"] for row in summarize(cfg)}
    for module, count in expected_counts(cfg).items():
        assert rows[module] == count, module


def test_default_is_paper_size():
    rows = {row["name"]: row for row in summarize(config.paper().net)}
    # paper: 686-d latent, generator FC(2096)-FC(4096)-FC(1372), fitness ends in 1024 features
    assert rows["ShapeEncoder"]["outputs"] == ((2, 686), (2, 686))
    assert rows["Generator"]["params"] == (686 * 2096 + 2 * 2096 + 2096 * 4096 + 2 * 4096
                                           + 4096 * 1372 + 1372)
    assert 100e6 < rows["FitnessNet"]["params"] < 150e6


def test_summary_cli_prints_counts(capsys, tiny_net):
    assert nets_cli.main(["--summary", "--config", "tiny"]) == 0
    out = capsys.readouterr().out
    rows = {row["name"]: row["params"] for row in summarize(tiny_net)}
    names = ("ShapeEncoder", "ShapeDecoder", "Generator", "FitnessNet", "FingerGenerator/embedding")
    for name in names:
        line = next(ln for ln in out.splitlines() if ln.startswith(name + " "))
        assert f"{rows[name]:,}" in line
    total = rows["ShapeEncoder"] + rows["ShapeDecoder"] + rows["Generator"] + rows["FitnessNet"]
    assert f"{total:,}" in out.splitlines()[-1]


# ---------------------------------------------------------------- running the tiny nets


def _changed(new, old) -> bool:
    return any(jax.tree.leaves(jax.tree.map(lambda a, b: bool(jnp.any(a != b)), new, old)))


def test_generator_and_fitness_jit_and_run(tiny_net, volumes):
    lat = tiny_net.latent_dim
    cases = [
        (Generator(tiny_net), jnp.tanh(jax.random.normal(jax.random.key(1), (2, lat)))),
        (FitnessNet(tiny_net), fitness_input(volumes, volumes, volumes)),
    ]
    for module, x in cases:
        variables = jit_init(module, 0, x)
        name = type(module).__name__
        assert count_params(variables["params"]) == expected_counts(tiny_net)[name]
        train_fn = jax.jit(lambda v, x, m=module: m.apply(v, x, train=True, mutable=["batch_stats"]))
        eval_fn = jax.jit(lambda v, x, m=module: m.apply(v, x, train=False))
        out, updates = train_fn(variables, x)
        evaluated = eval_fn(variables, x)
        for leaf in jax.tree.leaves(out) + jax.tree.leaves(evaluated):
            assert bool(jnp.all(jnp.isfinite(leaf))), type(module).__name__
        # training mode normalises with batch statistics and moves the running ones
        assert _changed(updates["batch_stats"], variables["batch_stats"]), type(module).__name__
        assert _changed(out, evaluated), type(module).__name__
    assert out.shape == (2, 11)


def test_autoencoder_jit_train_and_eval(tiny_net, volumes, ae_variables):
    """Encoder and decoder, compiled together, in both modes; the latent sample needs a key."""
    ae = ShapeAutoEncoder(tiny_net)
    with pytest.raises(ValueError, match="PRNG key"):
        jax.eval_shape(lambda v, x: ae.apply(v, x, train=True, mutable=["batch_stats"]),
                       ae_variables, volumes)

    @jax.jit
    def run(variables, x, keys):
        train_out = [ae.apply(variables, x, train=True, key=k, mutable=["batch_stats"])
                     for k in keys]
        recon, mu, logvar = ae.apply(variables, x, train=False)
        direct = ae.apply(variables, mu, train=False, method=ShapeAutoEncoder.decode)
        return train_out, (recon, mu, logvar), direct

    keys = [jax.random.key(1), jax.random.key(2), jax.random.key(1)]
    train_out, (recon, mu, logvar), direct = run(ae_variables, volumes, keys)
    (a, _, _), upd = train_out[0]
    b, a2 = train_out[1][0][0], train_out[2][0][0]
    lat = tiny_net.latent_dim
    assert a.shape == recon.shape == (2, R, R, R)
    assert mu.shape == logvar.shape == (2, lat)
    assert float(jnp.max(jnp.abs(mu))) < 1.0  # tanh: the paper's [-1, 1] latent
    assert bool(jnp.all(a == a2)) and bool(jnp.any(a != b))  # the key alone decides the sample
    np.testing.assert_allclose(recon, direct, atol=1e-6)  # evaluation decodes the mean
    assert _changed(upd["batch_stats"], ae_variables["batch_stats"])
    for leaf in jax.tree.leaves((train_out, recon, mu, logvar)):
        assert bool(jnp.all(jnp.isfinite(leaf)))


def test_wrong_volume_shapes_are_refused(tiny_net):
    key = jax.random.key(0)
    with pytest.raises(VolumeError, match=r"\[B, 40, 40, 40\]"):
        jax.eval_shape(lambda x: ShapeEncoder(tiny_net).init(key, x, train=False),
                       jnp.zeros((40, 40, 40)))
    with pytest.raises(VolumeError, match="FitnessNet"):
        jax.eval_shape(lambda x: FitnessNet(tiny_net).init(key, x, train=False),
                       jnp.zeros((2, 40, 40, 40)))
    with pytest.raises(VolumeError, match="right finger"):
        fitness_input(jnp.zeros((40, 40, 40)), jnp.zeros((40, 40, 40)), jnp.zeros((40, 40)))


def test_finger_generator_parts_are_separable_and_frozen(tiny_net, volumes, ae_variables):
    fg = FingerGenerator(tiny_net)
    shapes = jax.eval_shape(lambda k: fg.init(k, volumes, train=False), jax.random.key(0))
    assert set(shapes["params"]) == {"encoder", "embedding", "decoder"}
    # pretrained auto-encoder weights and a fresh embedding net fill it exactly
    gen_vars = jit_init(Generator(tiny_net), 3, jnp.zeros((2, tiny_net.latent_dim)))
    params = {**ae_variables["params"], "embedding": gen_vars["params"]}
    stats = {**ae_variables["batch_stats"], "embedding": gen_vars["batch_stats"]}
    assert (jax.tree.map(lambda a: a.shape, {"params": params, "batch_stats": stats})
            == jax.tree.map(lambda a: a.shape, shapes))

    ae, dec = ShapeAutoEncoder(tiny_net), ShapeDecoder(tiny_net)

    @jax.jit
    def run(params, stats, x):
        def loss(p):
            (left, right), upd = fg.apply({"params": p, "batch_stats": stats}, x, train=True,
                                          mutable=["batch_stats"])
            return jnp.mean(left) - jnp.mean(right), upd

        grads, upd = jax.grad(loss, has_aux=True)(params)
        v = {"params": params, "batch_stats": stats}
        mu_ae, _ = ae.apply(ae_variables, x, method=ShapeAutoEncoder.encode)
        mu_fg = fg.apply(v, x, method=FingerGenerator.object_latent)
        lz, rz = fg.apply(v, x, train=False, method=FingerGenerator.latents)
        left, right = fg.apply(v, x, train=False)
        dvars = {"params": params["decoder"], "batch_stats": stats["decoder"]}
        decoded = dec.apply(dvars, jnp.concatenate([lz, rz]), train=False)
        return grads, upd, mu_ae, mu_fg, (left, right), decoded

    grads, upd, mu_ae, mu_fg, (left, right), decoded = run(params, stats, volumes)
    np.testing.assert_allclose(mu_ae, mu_fg, atol=1e-6)
    norm = {k: sum(float(jnp.sum(jnp.square(g))) for g in jax.tree.leaves(v))
            for k, v in grads.items()}
    assert norm["encoder"] == 0.0  # cut from the graph: no backward pass through the encoder
    assert norm["embedding"] > 0.0 and norm["decoder"] > 0.0
    # only the embedding's BatchNorm statistics move in training mode
    for part in ("encoder", "decoder"):
        assert not _changed(upd["batch_stats"][part], stats[part]), part
    assert _changed(upd["batch_stats"]["embedding"], stats["embedding"])
    # the fingers are the frozen decoder's reading of the embedding's latents
    np.testing.assert_allclose(left, decoded[:2], atol=1e-5)
    np.testing.assert_allclose(right, decoded[2:], atol=1e-5)
    assert left.shape == right.shape == (2, R, R, R)


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


def test_decoder_kernels_old_checkpoints_and_bad_tails():
    """A config saved before ``decoder_kernels`` existed decodes as it did (3^3 kernels, 40
    voxels); kernel lists that do not fit the strides are refused before any work."""
    import dataclasses

    from f2f_jax.train.checkpoint import config_from_dict, config_to_dict

    saved = config_to_dict(config.default())
    saved["net"].update(decoder_channels=[8, 4, 2, 1], decoder_strides=[3, 3, 1, 1])
    del saved["net"]["decoder_kernels"]  # the first default, as its run directories hold it
    old = config_from_dict(saved).net
    dec = ShapeDecoder(old)
    assert dec.kernels() == (3, 3, 3, 3) and dec.output_sizes() == [12, 36, 38, 40]
    assert ShapeDecoder(config.default().net).output_sizes() == [13, 40]
    z = jnp.zeros((1, old.latent_dim))
    for kernels, words in (((4,), "differ in length"), ((2, 4), "at least their strides")):
        bad = dataclasses.replace(config.tiny().net, decoder_kernels=kernels)
        with pytest.raises(ValueError, match=words):
            ShapeDecoder(bad).init(jax.random.key(0), z[:, :bad.latent_dim], train=False)


@pytest.mark.parametrize("kernel,stride", [(3, 1), (3, 2), (3, 3), (7, 3), (4, 3), (5, 2)])
def test_transpose_conv_matches_lax(kernel, stride):
    # (3, 1): a padded convolution; (3, 3): one block per voxel; the rest: one convolution per
    # output phase
    x = jax.random.normal(jax.random.key(0), (2, 4, 5, 3, 3))
    m = VolumeConvTranspose(2, kernel, stride)
    kern = m.init(jax.random.key(1), x)["params"]["kernel"]

    def ours(x, kern):
        return m.apply({"params": {"kernel": kern}}, x)

    def lax_transpose(x, kern):
        return jax.lax.conv_transpose(x, kern, (stride,) * 3, "VALID",
                                      dimension_numbers=("NDHWC", "DHWIO", "NDHWC"))

    out = ours(x, kern)
    # (n - 1) s + k per axis
    assert out.shape == (2, 3 * stride + kernel, 4 * stride + kernel, 2 * stride + kernel, 2)
    np.testing.assert_allclose(out, lax_transpose(x, kern), rtol=1e-4, atol=1e-4)
    # training sees the gradients: both routes give lax's, for the input and the kernel
    w = jax.random.normal(jax.random.key(2), out.shape)
    grads = [jax.grad(lambda x, kern, f=f: jnp.sum(f(x, kern) * w), (0, 1))(x, kern)
             for f in (ours, lax_transpose)]
    for got, want in zip(*grads):
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-3)


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


def test_tiny_autoencoder_overfits_four_shapes(tiny_net, ae_variables):
    shapes = jnp.asarray(_sphere_tsdfs(4, seed=0))
    ae = ShapeAutoEncoder(tiny_net)
    variables = ae_variables
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

    keys = jax.random.split(jax.random.key(1), 16)
    losses = []
    for key in keys:
        state, loss = step(state, key)
        losses.append(loss)
    losses = np.asarray(jax.device_get(losses))
    assert np.all(np.isfinite(losses))
    assert losses[-3:].mean() < 0.5 * losses[:3].mean(), losses
