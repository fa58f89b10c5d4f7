"""Config from the command line: ``--set SECTION.FIELD=VALUE`` assignments on a ``Config``."""

from __future__ import annotations

import ast
import dataclasses

from f2f_jax.config import Config

SECTIONS = ("geometry", "sim", "net", "train")


def override(cfg: Config, assignments) -> Config:
    """``cfg`` with ``SECTION.FIELD=VALUE`` assignments applied in order (the command lines'
    ``--set``), e.g. ``["train.generator_lr=3e-4", "sim.timestep=0.002", "net.fitness_fc=(256, 128)"]``.

    Every field of the four sections can be set; the value is read as the field's type (int,
    float, bool, str, a tuple, or None where the field allows it) and anything else is refused
    with a ValueError that names the field and what it takes.
    """
    for text in assignments:
        key, sep, raw = str(text).partition("=")
        section, dot, name = key.strip().partition(".")
        if not sep or not dot or not name:
            raise ValueError(f"--set {text!r}: expected SECTION.FIELD=VALUE, e.g. train.generator_lr=3e-4")
        if section not in SECTIONS:
            raise ValueError(f"--set {key}: no config section {section!r}; choose one of "
                             f"{', '.join(SECTIONS)}")
        part = getattr(cfg, section)
        fields = {f.name: f for f in dataclasses.fields(part)}
        if name not in fields:
            raise ValueError(f"--set {key}: {section} has no field {name!r}; its fields: {', '.join(fields)}")
        value = _read_value(raw.strip(), str(fields[name].type), key.strip())
        cfg = cfg.replace(**{section: dataclasses.replace(part, **{name: value})})
    return cfg


def _read_value(raw: str, annotation: str, key: str):
    """``raw`` as a value of the field type ``annotation`` (the dataclass's annotation string)."""
    base = annotation.replace("| None", "").strip()
    kind = f"{'an' if base[0] in 'aeiou' else 'a'} {base}"
    if raw.lower() == "none":
        if "None" in annotation:
            return None
        raise ValueError(f"--set {key}=None: {key} takes {kind}, not None")
    if base == "str":
        return raw
    if base == "bool":
        if raw.lower() in ("true", "false"):
            return raw.lower() == "true"
        raise ValueError(f"--set {key}={raw}: {key} takes true or false")
    try:
        value = ast.literal_eval(raw)
    except (ValueError, SyntaxError):
        raise ValueError(f"--set {key}={raw}: {key} takes {kind}") from None
    if base == "int" and isinstance(value, int) and not isinstance(value, bool):
        return value
    if base == "float" and isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if base.startswith("tuple") and isinstance(value, (tuple, list)):
        return tuple(tuple(v) if isinstance(v, list) else v for v in value)
    raise ValueError(f"--set {key}={raw}: {key} takes {kind}")
