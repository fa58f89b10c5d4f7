"""Exception types: each says which input was wrong and how."""


class F2FError(Exception):
    """Base class of every error f2f_jax raises on purpose."""


class ConfigError(F2FError, ValueError):
    """A configuration field outside what it may hold (a generator, an anchor target, a count)."""


class MeshError(F2FError, ValueError):
    """A mesh that cannot become a shape volume (empty, NaN, flat, absurd size, unreadable)."""


class VolumeError(F2FError, ValueError):
    """A TSDF array of the wrong shape, dtype or content (NaN, empty, all inside)."""


class DecompositionError(F2FError, RuntimeError):
    """A shape that could not be cut into convex pieces."""


class CheckpointError(F2FError, RuntimeError):
    """No usable checkpoint, or one made for another configuration."""


class MissingExtraError(F2FError, ImportError):
    """An optional part (ray, warp, pybullet) asked for without its extra installed; the message
    names the install command."""
