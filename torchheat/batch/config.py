"""The run's YAML config: keys, validation (:func:`load_config`), the executor spec, and
the options hash that keys every record.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any, Protocol

_LOADERS = ("tosca_remeshed_5k", "tosca_remeshed_5k_symmetry", "scape", "tosca_hires", "kids",
            "shrec16_partial",
            "folder")


_TASKS = ("match", "symmetry")


_CONFIG_KEYS = {"name", "dataset", "dataset_args", "task", "match", "prepare", "limit",
                "eval_points", "output", "pictures", "distortion", "cache", "executor"}


_PREPARE_KEYS = {"k", "feature_time", "rtol", "kind", "boundary"}


class ConfigError(ValueError):
    """A missing or invalid run configuration."""


class Executor(Protocol):
    """Anything with ``map(fn, iterable) -> iterable of results`` (order may differ)."""

    def map(self, fn: Callable[[Any], Any], iterable: Iterable[Any]) -> Iterable[Any]: ...


# --------------------------------------------------------------------------------------------
# configuration
# --------------------------------------------------------------------------------------------
def load_config(config: str | os.PathLike | Mapping[str, Any]) -> dict[str, Any]:
    """Read (YAML file) or take (mapping) a run configuration, validate it, fill defaults.

    Parameters
    ----------
    config : path-like or mapping
        A YAML file or an already parsed dict.

    Returns
    -------
    dict
        Keys ``name, dataset, dataset_args, task, match, prepare, limit, eval_points, output,
        pictures, distortion, cache, executor`` (``output`` defaults to ``out/<name>``;
        ``cache``: None or the folder of the per-shape disk cache, ``true`` meaning
        :func:`torchheat.datasets.default_cache_dir`; ``executor``: ``{}`` (in-process),
        ``{"workers": N}`` or ``{"dask": ADDRESS}``).

    Raises
    ------
    ConfigError
        With a one-line explanation.

    Examples
    --------
    >>> cfg = load_config({"name": "x", "dataset": "scape"})
    >>> cfg["task"], cfg["output"], cfg["pictures"]
    ('match', 'out/x', 3)
    """
    if isinstance(config, Mapping):
        raw: Any = dict(config)
        where = "config"
    else:
        path = Path(config)
        where = str(path)
        if not path.is_file():
            raise ConfigError(f"config file {path} not found")
        import yaml

        try:
            raw = yaml.safe_load(path.read_text())
        except yaml.YAMLError as exc:
            raise ConfigError(f"{path}: invalid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(raw, dict):
        raise ConfigError(f"{where}: expected a mapping of settings at the top level")
    unknown = set(raw) - _CONFIG_KEYS
    if unknown:
        raise ConfigError(f"{where}: unknown keys {sorted(unknown)}; allowed: "
                          f"{sorted(_CONFIG_KEYS)}")
    cfg: dict[str, Any] = {
        "name": raw.get("name"),
        "dataset": raw.get("dataset"),
        "dataset_args": raw.get("dataset_args") or {},
        "task": raw.get("task", "match"),
        "match": raw.get("match") or {},
        "prepare": raw.get("prepare") or {},
        "limit": raw.get("limit"),
        "eval_points": raw.get("eval_points"),
        "output": raw.get("output"),
        "pictures": raw.get("pictures", 3),
        "distortion": raw.get("distortion", False),
        "cache": raw.get("cache", False),
        "executor": raw.get("executor") or {},
    }
    if not isinstance(cfg["name"], str) or not cfg["name"].strip():
        raise ConfigError(f"{where}: 'name' (a non-empty string) is required")
    if cfg["dataset"] not in _LOADERS:
        raise ConfigError(f"{where}: 'dataset' must be one of {list(_LOADERS)}, "
                          f"got {cfg['dataset']!r}")
    for key in ("dataset_args", "match", "prepare"):
        if not isinstance(cfg[key], dict):
            raise ConfigError(f"{where}: '{key}' must be a mapping")
    if cfg["task"] not in _TASKS:
        raise ConfigError(f"{where}: 'task' must be one of {list(_TASKS)}, got {cfg['task']!r}")
    from ..matching.options import _PREPARE_LEAST, _check_numbers
    from ..matching.pipeline import check_options  # (imports torch, as the run will)
    from ..operators import check_kind

    # a misspelt or meaningless option failed every pair, each after its eigensolves
    try:
        check_options(cfg["match"])
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: match: {exc}") from None
    pp = cfg["prepare"]
    try:
        _check_numbers({k: v for k, v in pp.items() if k in _PREPARE_LEAST}, _PREPARE_LEAST)
        check_kind(pp.get("kind") or "cotan", pp.get("boundary") or "neumann")
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: prepare: {exc}") from None
    bad = set(cfg["prepare"]) - _PREPARE_KEYS
    if bad:
        raise ConfigError(f"{where}: unknown prepare options {sorted(bad)}; allowed: "
                          f"{sorted(_PREPARE_KEYS)}")
    for key in ("limit", "eval_points"):
        v = cfg[key]
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
            raise ConfigError(f"{where}: '{key}' must be a positive integer or null, got {v!r}")
    p = cfg["pictures"]
    if isinstance(p, bool) or not isinstance(p, int) or p < 0:
        raise ConfigError(f"{where}: 'pictures' must be an integer >= 0, got {p!r}")
    if not isinstance(cfg["distortion"], bool):
        raise ConfigError(f"{where}: 'distortion' must be true or false")
    c = cfg["cache"]
    if c is None or c is False:
        cfg["cache"] = None
    elif c is True:
        from ..datasets import default_cache_dir

        cfg["cache"] = str(default_cache_dir())
    elif isinstance(c, str) and c.strip():
        cfg["cache"] = c
    else:
        raise ConfigError(f"{where}: 'cache' must be true, false or a folder, got {c!r}")
    cfg["executor"] = _check_executor(cfg["executor"], where)
    if cfg["output"] is None:
        cfg["output"] = f"out/{cfg['name']}"
    cfg["output"] = str(cfg["output"])
    if cfg["dataset"] == "folder" and "path" not in cfg["dataset_args"]:
        raise ConfigError(f"{where}: dataset 'folder' needs dataset_args.path and .pairs")
    if cfg["dataset"] == "folder" and cfg["dataset_args"].get("gt") != "identity":
        # the errors of a batch are only as true as its ground truth, and a folder has none
        # but the vertex order: assuming it silently scored unrelated meshes as if matched
        raise ConfigError(
            f"{where}: dataset 'folder' needs dataset_args.gt: identity (got "
            f"{cfg['dataset_args'].get('gt')!r}; the meshes share "
            "their vertex order, vertex i of one is vertex i of every other, as poses of one "
            "template); a folder carries no other ground truth. To compute maps without "
            "ground truth, run 'torchheat match' on each pair")
    return cfg


def _check_executor(spec: Any, where: str) -> dict[str, Any]:
    """``executor: {dask: ADDRESS}`` or ``{workers: N}`` (or nothing: in-process)."""
    if not isinstance(spec, dict) or set(spec) - {"dask", "workers"} or len(spec) > 1:
        raise ConfigError(f"{where}: 'executor' must be {{dask: ADDRESS}} (local, local:N or "
                          f"tcp://HOST:PORT) or {{workers: N}}, got {spec!r}")
    if "workers" in spec:
        n = spec["workers"]
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise ConfigError(f"{where}: executor.workers must be an integer >= 1, got {n!r}")
    if "dask" in spec:
        from ..executors import ExecutorError, parse_dask_address

        try:
            parse_dask_address(spec["dask"])
        except ExecutorError as exc:
            raise ConfigError(f"{where}: executor.dask: {exc}") from None
    return dict(spec)


def options_hash(cfg: Mapping[str, Any]) -> str:
    """Hash (12 hex characters) of what determines a pair's result: task, match, prepare and
    eval_points settings.

    Examples
    --------
    >>> a = options_hash({"task": "match", "match": {"method": "paper"}})
    >>> a == options_hash({"task": "match", "match": {"method": "paper"}, "prepare": {}})
    True
    """
    payload = json.dumps(
        {"task": cfg.get("task", "match"), "match": dict(cfg.get("match") or {}),
         "prepare": dict(cfg.get("prepare") or {}), "eval_points": cfg.get("eval_points")},
        sort_keys=True, default=str,
    )
    return hashlib.sha256(payload.encode()).hexdigest()[:12]
