"""Where psprm finds its configuration (robots, scenes, settings) and its caches."""

from __future__ import annotations

import os
from pathlib import Path

from .errors import ConfigError


def project_root() -> Path:
    return Path(__file__).resolve().parent.parent


def config_dir() -> Path:
    """``$PSPRM_CONFIG_DIR`` if set, else the repository's ``config/`` folder."""
    env = os.environ.get("PSPRM_CONFIG_DIR")
    return Path(env) if env else project_root() / "config"


def cache_dir() -> Path:
    """``$PSPRM_CACHE_DIR`` if set, else ``~/.cache/psprm`` (derived URDFs, sphere models, detector weights)."""
    env = os.environ.get("PSPRM_CACHE_DIR")
    d = Path(env) if env else Path.home() / ".cache" / "psprm"
    d.mkdir(parents=True, exist_ok=True)
    return d


def resolve_named(kind: str, name_or_path: str) -> Path:
    """Resolve a robot/scene given by name (``home``) or by path (``my/scene.yaml``)."""
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml"):
        if not p.is_file():
            raise ConfigError(str(p), "", f"{kind} file not found")
        return p
    cand = config_dir() / f"{kind}s" / f"{name_or_path}.yaml"
    if not cand.is_file():
        known = sorted(x.stem for x in (config_dir() / f"{kind}s").glob("*.yaml"))
        raise ConfigError(str(cand), "", f"unknown {kind} '{name_or_path}' (known: {', '.join(known) or 'none'})")
    return cand
