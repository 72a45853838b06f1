"""Configuration: YAML defaults (configs/default.yaml, the paper's values), a user YAML on top,
then `section.key=value` overrides from the command line."""

from __future__ import annotations

import copy
from dataclasses import fields
from pathlib import Path

import yaml

CONFIG_DIR = Path(__file__).resolve().parent / "configs"
DEFAULT = CONFIG_DIR / "default.yaml"


def _merge(base: dict, top: dict, where: str = "") -> dict:
    out = copy.deepcopy(base)
    for key, value in (top or {}).items():
        if key not in out:
            raise KeyError(f"unknown setting {where}{key}; known: {sorted(out)}")
        if isinstance(out[key], dict) and isinstance(value, dict):
            out[key] = _merge(out[key], value, f"{where}{key}.")
        else:
            out[key] = value
    return out


def parse_override(text: str) -> dict:
    """'estimator.window=1.0' -> {'estimator': {'window': 1.0}} (value parsed as YAML)."""
    if "=" not in text:
        raise ValueError(f"override {text!r} must look like section.key=value")
    path, value = text.split("=", 1)
    node: dict = {}
    out = node
    keys = path.strip().split(".")
    for k in keys[:-1]:
        node[k] = {}
        node = node[k]
    node[keys[-1]] = yaml.safe_load(value)
    return out


def load_config(path: str | Path | None = None, overrides: list[str] | None = None) -> dict:
    """Defaults, then the YAML at `path`, then `overrides`; unknown keys are an error."""
    cfg = yaml.safe_load(DEFAULT.read_text())
    if path is not None:
        try:
            user = yaml.safe_load(Path(path).read_text()) or {}
        except FileNotFoundError:
            raise FileNotFoundError(f"config file not found: {path}") from None
        cfg = _merge(cfg, user)
    for text in overrides or []:
        cfg = _merge(cfg, parse_override(text))
    return cfg


def dataclass_from_dict(cls, d: dict | None, section: str):
    """cls(**d) for a settings dataclass, naming unknown keys of `section` in the error."""
    d = dict(d or {})
    known = {f.name for f in fields(cls)}
    unknown = set(d) - known
    if unknown:
        raise ValueError(f"unknown {section} settings {sorted(unknown)}; known: {sorted(known)}")
    return cls(**d)
