"""Shape auto-encoder: TSDF volumes <-> points of the [-1, 1]^latent shape space.

Layer lists follow the paper's appendix B.2 and the original code (``learning/featureExtractor.py``):

* ``ShapeEncoder``: nine 3^3 convolutions without padding, the fifth with stride 2, each followed by
  BatchNorm and leaky ReLU: 40 -> 38 -> 36 -> 34 -> 32 -> 15 -> 13 -> 11 -> 9 -> 7 voxels, 4 channels
  (4 x 7^3 = 1372 = 2 x 686 features).  The original split these activations directly into mu and
  logvar after the last leaky ReLU, which squeezes negative mu by 100x.  We flatten and add two
  dense heads (mu with tanh, logvar), which also makes any channel width work with any latent size.
* ``ShapeDecoder``: FC(1024)-FC(2048)-FC(4096), reshape to 4^3 x 64 (4096 = 64 x 4^3), then eleven
  3^3 transposed convolutions without padding, CT(64,1)-CT(64,1)-CT(32,3)-CT(16,1)-CT(8,1)-CT(4,1)-
  CT(2,1)-CT(1,1) x 4: 4 -> 6 -> 8 -> 24 -> 26 -> ... -> 40 (a VALID transposed convolution of
  kernel k and stride s maps n to (n - 1) s + k).  BatchNorm and leaky ReLU after every layer but
  the last, which has a bias and tanh ("CT(1,3,1)-TanH" in the paper; the original code also put a
  BatchNorm before that tanh, which slowed fitting the TSDF's mostly-positive level).
* ``ShapeAutoEncoder``: the VAE used to pretrain both.  Its sample is ``mu + exp(logvar / 2) * eps``
  with an explicit PRNG key in training and ``mu`` in evaluation.

Volumes enter and leave as ``[B, 40, 40, 40]`` (channels added and removed inside: the convolutions
run channels-last, ``[B, D, H, W, C]``).  ``VolumeConv`` and ``VolumeConvTranspose`` are the 3D
(transposed) convolutions of every net here; they choose cheaper but equivalent formulations where
XLA's general 3D convolution is slow (few channels on the CPU, non-overlapping transposed kernels).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import linen as nn

from f2f_jax.config import GeometryConfig, NetConfig
from f2f_jax.errors import VolumeError

RESOLUTION = GeometryConfig().resolution  # 40: every volume the nets see is 40^3
# the truncation (voxels) of the finger TSDFs the height generator writes: the geometry's, so the
# fitness net sees imprint-like volumes
TRUNCATION_VOXELS = GeometryConfig().truncation_voxels


def check_volume_batch(x: jax.Array, name: str, resolution: int = RESOLUTION) -> None:
    """Raise VolumeError unless ``x`` is a batch of volumes ``[B, R, R, R]`` (checked at trace time)."""
    r = resolution
    if x.ndim != 4 or tuple(x.shape[1:]) != (r, r, r):
        raise VolumeError(f"{name}: expected a batch of volumes [B, {r}, {r}, {r}], got shape "
                          f"{tuple(x.shape)}")


def batch_norm(cfg: NetConfig, train: bool, dtype: Any, name: str | None = None) -> nn.BatchNorm:
    # epsilon 1e-5 as PyTorch's BatchNorm, which the original used
    return nn.BatchNorm(use_running_average=not train, momentum=cfg.bn_momentum, epsilon=1e-5,
                        dtype=dtype, name=name)


# Below this many (input x output) channel pairs a 3D convolution runs on the CPU as one 2D
# convolution: the k depth-shifted copies of the input are stacked along channels and depth is
# folded into the batch.  XLA's CPU 3D convolution costs far more than its arithmetic for few
# channels; measured on 2 cores, batch 4 x 34^3, forward / forward + gradients:
#   1 -> 1 channels: 33 / 75 ms as 3D, 6 / 10 ms as 2D;   4 -> 4: 117 / 300 ms against 9 / 54 ms;
#   8 -> 8: 46 / 177 ms against 60 / 180 ms (no gain from here up).
# Accelerators keep the library's 3D convolution.
_FOLD_DEPTH_MAX_PAIRS = 32


def _use_fold_depth(in_channels: int, out_channels: int) -> bool:
    return in_channels * out_channels <= _FOLD_DEPTH_MAX_PAIRS and jax.default_backend() == "cpu"


def _fold_depth_conv(x: jax.Array, kernel: jax.Array, stride: int) -> jax.Array:
    """VALID 3D cross-correlation of ``x`` [B, D, H, W, I] with ``kernel`` [k, k, k, I, O] as 2D.

    ``y[b, d] = sum_i conv2d(x[b, s d + i], kernel[i])`` over the k depth taps; stacking the taps
    along channels makes that one 2D convolution with k x I input channels.
    """
    k = kernel.shape[0]
    b, d, h, w, c = x.shape
    d_out = (d - k) // stride + 1
    taps = [x[:, i: i + stride * (d_out - 1) + 1: stride] for i in range(k)]
    stacked = jnp.concatenate(taps, axis=-1).reshape(b * d_out, h, w, k * c)
    # [k_d, k_h, k_w, I, O] -> [k_h, k_w, k_d * I, O], matching the tap-major channel order above
    kernel_2d = jnp.transpose(kernel, (1, 2, 0, 3, 4)).reshape(k, k, k * c, kernel.shape[-1])
    y = jax.lax.conv_general_dilated(stacked, kernel_2d, (stride, stride), "VALID",
                                     dimension_numbers=("NHWC", "HWIO", "NHWC"))
    return y.reshape(b, d_out, *y.shape[1:])


def conv3d(x: jax.Array, kernel: jax.Array, stride: int = 1, padding: int = 0) -> jax.Array:
    """3D cross-correlation, the same result on every path.

    x: [B, D, H, W, I]; kernel: [k, k, k, I, O]; ``padding`` zero voxels on every side.
    Returns [B, (D + 2 p - k) // s + 1, ..., O].
    """
    if _use_fold_depth(kernel.shape[-2], kernel.shape[-1]):
        p = padding
        xp = jnp.pad(x, ((0, 0), (p, p), (p, p), (p, p), (0, 0))) if p else x
        return _fold_depth_conv(xp, kernel, stride)
    return jax.lax.conv_general_dilated(x, kernel, (stride,) * 3, [(padding, padding)] * 3,
                                        dimension_numbers=("NDHWC", "DHWIO", "NDHWC"))


def dense_layers(x: jax.Array, widths, cfg: NetConfig, train: bool, dtype: Any) -> jax.Array:
    """Dense (no bias) -> BatchNorm -> leaky ReLU for each width, inside the calling module's
    compact context (the layers are named Dense_i, BatchNorm_i as if written inline)."""
    for width in widths:
        x = nn.Dense(width, use_bias=False, dtype=dtype)(x)
        x = batch_norm(cfg, train, dtype)(x)
        x = nn.leaky_relu(x, cfg.leaky_slope)
    return x


class Net(nn.Module):
    """A Fit2Form network: sized by ``config`` (NetConfig), computing in ``dtype`` (float32;
    bfloat16 on accelerators) while its parameters stay float32."""

    config: NetConfig
    dtype: Any = jnp.float32


class VolumeConv(nn.Module):
    """3D convolution (cross-correlation) on ``[B, D, H, W, C]``: cube kernel, one stride, padding.

    Same parameters as ``flax.linen.Conv`` (``kernel`` [k, k, k, in, out], optional ``bias``),
    but few-channel layers take a faster path on the CPU (see ``_FOLD_DEPTH_MAX_PAIRS``).
    """

    features: int
    kernel_size: int = 3
    stride: int = 1
    padding: int = 0  # voxels of zeros on every side
    use_bias: bool = False
    dtype: Any = jnp.float32

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        k, c_in = self.kernel_size, x.shape[-1]
        kernel = self.param("kernel", nn.initializers.lecun_normal(), (k, k, k, c_in, self.features),
                            jnp.float32).astype(self.dtype)
        y = conv3d(x.astype(self.dtype), kernel, self.stride, self.padding)
        if self.use_bias:
            y = y + self.param("bias", nn.initializers.zeros, (self.features,), jnp.float32).astype(
                self.dtype)
        return y


def _phase_conv_transpose(x: jax.Array, kernel: jax.Array, s: int) -> jax.Array:
    """VALID transposed convolution of stride ``s`` and any cube kernel, as one convolution at the
    input's resolution and a depth-to-space reshape (the same values as ``lax.conv_transpose``).

    Output voxel ``s m + r`` (per axis) sums ``x[m - t] V[s t + r]`` over ``t`` in ``0..q-1``,
    ``q = ceil(k / s)``, where ``V`` is the flipped kernel padded with zeros to ``s q``: for each
    phase ``r`` that is a VALID correlation of ``x`` padded by ``q - 1`` with a ``q^3`` kernel, so
    all ``s^3`` phases are one convolution with ``s^3 x out`` channels.  XLA's own transposed
    convolution first dilates the input with ``s - 1`` zeros between voxels and correlates the
    ``k^3`` kernel over it: ``s^3`` times the multiplications, most of them by zero.
    """
    k, c_in, c_out = kernel.shape[0], kernel.shape[3], kernel.shape[4]
    q = -(-k // s)
    v = jnp.pad(kernel[::-1, ::-1, ::-1], [(0, s * q - k)] * 3 + [(0, 0), (0, 0)])
    # [a = s t + r per axis] -> [t, r] per axis, t reversed: correlation order
    v = v.reshape(q, s, q, s, q, s, c_in, c_out)[::-1, :, ::-1, :, ::-1]
    phases = jnp.transpose(v, (0, 2, 4, 6, 1, 3, 5, 7)).reshape(q, q, q, c_in, s ** 3 * c_out)
    z = conv3d(x, phases, 1, q - 1)  # [B, D + q - 1, H + q - 1, W + q - 1, (r_d, r_h, r_w, out)]
    b, md, mh, mw = z.shape[:4]
    z = z.reshape(b, md, mh, mw, s, s, s, c_out).transpose(0, 1, 4, 2, 5, 3, 6, 7)
    z = z.reshape(b, md * s, mh * s, mw * s, c_out)
    d, h, w = ((n - 1) * s + k for n in x.shape[1:4])
    return z[:, :d, :h, :w]


class VolumeConvTranspose(nn.Module):
    """Transposed 3D convolution without padding (VALID): edge n -> (n - 1) * stride + kernel.

    Computes what ``jax.lax.conv_transpose(x, kernel, strides, "VALID")`` (and so
    ``flax.linen.ConvTranspose(padding="VALID")``) computes, by cheaper routes: stride 1 is a
    convolution with ``kernel - 1`` voxels of zero padding; stride == kernel (no overlap) writes
    one k^3 block per input voxel, a matrix product and a reshape; any other stride is one
    convolution per output phase at the input's resolution (``_phase_conv_transpose``).
    Parameters: ``kernel`` [k, k, k, in, out], optional ``bias``.
    """

    features: int
    kernel_size: int = 3
    stride: int = 1
    use_bias: bool = False
    dtype: Any = jnp.float32

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        k, s, c_in = self.kernel_size, self.stride, x.shape[-1]
        kernel = self.param("kernel", nn.initializers.lecun_normal(), (k, k, k, c_in, self.features),
                            jnp.float32).astype(self.dtype)
        x = x.astype(self.dtype)
        if s == 1:
            y = conv3d(x, kernel, 1, k - 1)
        elif s == k:
            b, d, h, w, _ = x.shape
            # lax.conv_transpose (no transpose_kernel) correlates with the flipped kernel here
            y = jnp.einsum("bdhwi,xyzio->bdxhywzo", x, kernel[::-1, ::-1, ::-1])
            y = y.reshape(b, d * k, h * k, w * k, self.features)
        else:
            y = _phase_conv_transpose(x, kernel, s)
        if self.use_bias:
            y = y + self.param("bias", nn.initializers.zeros, (self.features,), jnp.float32).astype(
                self.dtype)
        return y


def valid_conv_sizes(size: int, strides: tuple[int, ...], kernel: int = 3) -> list[int]:
    """Edge lengths after each VALID convolution: ``n -> (n - k) // s + 1``."""
    sizes = []
    for s in strides:
        size = (size - kernel) // s + 1
        sizes.append(size)
    return sizes


def valid_transpose_sizes(size: int, strides: tuple[int, ...], kernel: int | tuple[int, ...] = 3
                          ) -> list[int]:
    """Edge lengths after each VALID transposed convolution: ``n -> (n - 1) s + k`` (``kernel``:
    one size for all layers or one per layer)."""
    kernels = (kernel,) * len(strides) if isinstance(kernel, int) else tuple(kernel)
    sizes = []
    for s, k in zip(strides, kernels):
        size = (size - 1) * s + k
        sizes.append(size)
    return sizes


class ShapeEncoder(Net):
    """TSDF volume -> Gaussian posterior over the shape latent.

    Attributes
    ----------
    config: NetConfig (latent_dim, encoder_channels, encoder_strides, encoder_logvar_init, ...).
    dtype: computation dtype (float32; bfloat16 on accelerators); parameters stay float32.
    """

    @nn.compact
    def __call__(self, tsdf: jax.Array, *, train: bool) -> tuple[jax.Array, jax.Array]:
        """Encode volumes.

        Parameters
        ----------
        tsdf: [B, 40, 40, 40] float32, negative inside.
        train: BatchNorm uses batch statistics (and updates ``batch_stats``) when True.

        Returns
        -------
        mu: [B, latent_dim] float32 in (-1, 1) (tanh), the shape's point in latent space.
        logvar: [B, latent_dim] float32, log-variance of the posterior around mu.
        """
        cfg = self.config
        check_volume_batch(tsdf, "ShapeEncoder input")
        if len(cfg.encoder_strides) != len(cfg.encoder_channels):
            raise ValueError(f"encoder_strides {cfg.encoder_strides} and encoder_channels "
                             f"{cfg.encoder_channels} differ in length")
        if valid_conv_sizes(RESOLUTION, cfg.encoder_strides)[-1] < 1:
            raise ValueError(f"encoder_strides {cfg.encoder_strides} shrink a {RESOLUTION}^3 "
                             "volume to nothing")
        x = tsdf[..., None].astype(self.dtype)
        for channels, stride in zip(cfg.encoder_channels, cfg.encoder_strides):
            # no conv bias: the BatchNorm after it has its own shift
            x = VolumeConv(channels, 3, stride, dtype=self.dtype)(x)
            x = batch_norm(cfg, train, self.dtype)(x)
            x = nn.leaky_relu(x, cfg.leaky_slope)
        x = x.reshape(x.shape[0], -1)
        mu = jnp.tanh(nn.Dense(cfg.latent_dim, dtype=self.dtype, name="mu_head")(x))
        logvar = nn.Dense(cfg.latent_dim, dtype=self.dtype, name="logvar_head",
                          bias_init=nn.initializers.constant(cfg.encoder_logvar_init))(x)
        return mu.astype(jnp.float32), logvar.astype(jnp.float32)


class ShapeDecoder(Net):
    """Shape latent -> TSDF volume in [-1, 1].

    Attributes
    ----------
    config: NetConfig (latent_dim, decoder_fc, decoder_seed_size, decoder_channels,
        decoder_strides, ...).
    dtype: computation dtype; parameters stay float32.
    """

    def output_sizes(self) -> list[int]:
        """Edge length of the volume after each transposed convolution (last one must be 40)."""
        cfg = self.config
        return valid_transpose_sizes(cfg.decoder_seed_size, cfg.decoder_strides, self.kernels())

    def kernels(self) -> tuple[int, ...]:
        """Kernel edge of each transposed convolution (``decoder_kernels``; empty: all 3)."""
        cfg = self.config
        return tuple(cfg.decoder_kernels) or (3,) * len(cfg.decoder_strides)

    @nn.compact
    def __call__(self, latent: jax.Array, *, train: bool) -> jax.Array:
        """Decode latents.

        Parameters
        ----------
        latent: [B, latent_dim] float32, nominally in [-1, 1].
        train: BatchNorm uses batch statistics (and updates ``batch_stats``) when True.

        Returns
        -------
        tsdf: [B, 40, 40, 40] float32 in (-1, 1), negative inside.
        """
        cfg = self.config
        if latent.ndim != 2 or latent.shape[1] != cfg.latent_dim:
            raise ValueError(f"ShapeDecoder input: expected [B, {cfg.latent_dim}], got shape "
                             f"{tuple(latent.shape)}")
        seed = cfg.decoder_seed_size
        seed_channels, rem = divmod(cfg.decoder_fc[-1], seed ** 3)
        if rem or seed_channels < 1:
            raise ValueError(f"decoder_fc[-1] = {cfg.decoder_fc[-1]} is not a multiple of "
                             f"decoder_seed_size^3 = {seed ** 3}")
        if len(cfg.decoder_strides) != len(cfg.decoder_channels):
            raise ValueError(f"decoder_strides {cfg.decoder_strides} and decoder_channels "
                             f"{cfg.decoder_channels} differ in length")
        if cfg.decoder_kernels and len(cfg.decoder_kernels) != len(cfg.decoder_strides):
            raise ValueError(f"decoder_kernels {cfg.decoder_kernels} and decoder_strides "
                             f"{cfg.decoder_strides} differ in length")
        if any(k < s for k, s in zip(self.kernels(), cfg.decoder_strides)):
            raise ValueError(f"decoder_kernels {self.kernels()} must be at least their strides "
                             f"{cfg.decoder_strides} (shorter kernels leave gaps)")
        if cfg.decoder_channels[-1] != 1:
            raise ValueError(f"decoder_channels must end with 1 (one TSDF channel), got "
                             f"{cfg.decoder_channels}")
        if self.output_sizes()[-1] != RESOLUTION:
            raise ValueError(f"decoder layers grow {seed}^3 to {self.output_sizes()}, not to "
                             f"{RESOLUTION}^3")

        x = dense_layers(latent.astype(self.dtype), cfg.decoder_fc, cfg, train, self.dtype)
        x = x.reshape(x.shape[0], seed, seed, seed, seed_channels)
        n_layers = len(cfg.decoder_channels)
        layers = zip(cfg.decoder_channels, cfg.decoder_strides, self.kernels())
        for i, (channels, stride, kernel) in enumerate(layers):
            if i < n_layers - 1:
                x = VolumeConvTranspose(channels, kernel, stride, dtype=self.dtype)(x)
                x = nn.leaky_relu(batch_norm(cfg, train, self.dtype)(x), cfg.leaky_slope)
            else:
                # the output layer's own bias sets the TSDF's level (mostly +1, outside); a
                # BatchNorm here would first force every batch to zero mean and unit spread
                x = VolumeConvTranspose(channels, kernel, stride, use_bias=True, dtype=self.dtype)(x)
        return jnp.tanh(x[..., 0]).astype(jnp.float32)


class ShapeAutoEncoder(Net):
    """The VAE that pretrains ``ShapeEncoder`` and ``ShapeDecoder``.

    Its parameters are ``{"encoder": ..., "decoder": ...}``, the same subtrees (and names) that
    ``FingerGenerator`` uses, so pretrained weights move over unchanged.
    """

    def setup(self):
        self.encoder = ShapeEncoder(self.config, dtype=self.dtype)
        self.decoder = ShapeDecoder(self.config, dtype=self.dtype)

    def __call__(self, tsdf: jax.Array, *, train: bool,
                 key: jax.Array | None = None) -> tuple[jax.Array, jax.Array, jax.Array]:
        """Encode, sample, decode.

        Parameters
        ----------
        tsdf: [B, 40, 40, 40] float32, negative inside.
        train: sample the latent (``key`` required) and use batch statistics when True;
            decode the posterior mean with running statistics when False.
        key: PRNG key for the reparameterised sample; required when ``train``.

        Returns
        -------
        recon: [B, 40, 40, 40] float32 in (-1, 1).
        mu, logvar: [B, latent_dim] float32 each (see ``ShapeEncoder``).
        """
        mu, logvar = self.encoder(tsdf, train=train)
        if train:
            if key is None:
                raise ValueError("ShapeAutoEncoder(train=True) needs a PRNG key for its sample")
            latent = reparameterize(key, mu, logvar)
        else:
            latent = mu
        return self.decoder(latent, train=train), mu, logvar

    def encode(self, tsdf: jax.Array, *, train: bool = False) -> tuple[jax.Array, jax.Array]:
        """``ShapeEncoder`` alone: [B, 40, 40, 40] -> (mu, logvar), each [B, latent_dim]."""
        return self.encoder(tsdf, train=train)

    def decode(self, latent: jax.Array, *, train: bool = False) -> jax.Array:
        """``ShapeDecoder`` alone: [B, latent_dim] -> [B, 40, 40, 40]."""
        return self.decoder(latent, train=train)


def reparameterize(key: jax.Array, mu: jax.Array, logvar: jax.Array) -> jax.Array:
    """Sample ``mu + exp(logvar / 2) * eps``, ``eps ~ N(0, I)``: differentiable in mu and logvar.

    key: PRNG key. mu, logvar: [B, latent_dim] float32. Returns [B, latent_dim] float32.
    """
    eps = jax.random.normal(key, mu.shape, mu.dtype)
    return mu + jnp.exp(0.5 * logvar) * eps
