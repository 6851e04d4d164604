"""Replayable runs: what ``config.yaml`` records about the command, and reading it back.

``liris eval`` records the full command line, the working directory, the
liris version and the git commit of the liris source when it is a git
checkout. ``liris eval --config RUN/config.yaml`` turns the file back into
the command's options (:func:`config_defaults`), as *defaults*: every option
given on the command line still wins, so ``--config old/config.yaml --radius 5``
reruns the same evaluation at 5 m.

Descriptor parameters are replayed in full (each as ``--param NAME.KEY=VALUE``),
not only by preset name, so editing a preset file later does not change a
replayed run.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import yaml

from lidar_iris_eval import __version__
from lidar_iris_eval.config import AnyMapping, OneOf, check_schema
from lidar_iris_eval.errors import LirisError

#: ``open_sequence`` keyword (as stored in config.yaml) -> ``liris eval`` parameter name
READER_PARAMS = {
    "poses": "poses_path", "calib": "calib_path", "pose_format": "pose_format",
    "lidar_frame": "lidar_frame_poses", "times": "times_path", "topic": "topic",
    "pose_topic": "pose_topic", "stamps": "stamps", "tolerance": "tolerance",
    "frames": "frames", "every": "every", "min_distance": "min_distance",
    "dataset": "dataset", "scene": "scene",
}


#: what ``config.yaml`` may hold; unknown keys and wrong types are errors (as in --plan files)
RUN_CONFIG_SCHEMA: dict[str, Any] = {
    "version": str,
    "sequence": {"path": str, "name": str, "n_frames": int, "fingerprint": str,
                 "reader_options": AnyMapping},
    "descriptors": [{"name": str, "preset": str, "params": AnyMapping}],
    "protocols": [OneOf(1, 2, "1", "2")],
    "radius": float,
    "exclude": {"value": (int, None), "preset": (str, None), "seconds": (float, None)},
    "recall_denominator": OneOf("revisits", "accepted"),
    "distance": OneOf("3d", "planar"),
    "pose_frame": OneOf("camera", "lidar"),
    "candidates": (int, None),
    "block_pairs": int,
    "sensor": (str, None),
    "command": AnyMapping,
    "convention": AnyMapping,
    "engine": {"scheduler": OneOf("processes", "local", accept=lambda v: isinstance(v, str)
                                  and "://" in v, text="processes, local or tcp://HOST:PORT"),
               "workers": (int, None)},
    "loop_poses": AnyMapping,  # --refine, --gt-pose, RR thresholds, acceptance (issue 23)
    "seeds": [int],
    "odometry": OneOf("gt", "kiss-icp"),  # --odometry: the local maps' pose source (issue 28)
    "odometry_file": str,  # --odometry FILE: the .g2o vertices
}


def git_commit(path: str | os.PathLike | None = None) -> dict[str, Any] | None:
    """``{"commit": sha, "dirty": bool}`` of the git checkout holding ``path``, else None."""
    folder = Path(path) if path is not None else Path(__file__).resolve().parents[2]
    try:
        sha = subprocess.run(["git", "-C", str(folder), "rev-parse", "HEAD"], check=True,
                             capture_output=True, text=True, timeout=5).stdout.strip()
        status = subprocess.run(["git", "-C", str(folder), "status", "--porcelain",
                                 "--untracked-files=no"], check=True, capture_output=True,
                                text=True, timeout=10).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    return {"commit": sha, "dirty": bool(status.strip())} if sha else None


def provenance(argv: list[str] | None = None) -> dict[str, Any]:
    """How this run was started: argv, working directory, liris version, git commit."""
    argv = list(sys.argv if argv is None else argv)
    if argv and Path(argv[0]).name in ("liris", "__main__.py"):
        argv[0] = "liris"
    return {"argv": argv, "cwd": os.getcwd(), "liris_version": __version__,
            "git": git_commit()}


def read_config(path: str | os.PathLike) -> dict[str, Any]:
    """``config.yaml`` of a run (or the run folder itself) as a dict."""
    path = Path(path)
    if path.is_dir():
        path = path / "config.yaml"
    if not path.is_file():
        raise LirisError(path, "config file not found")
    try:
        config = yaml.safe_load(path.read_text())
    except (yaml.YAMLError, UnicodeDecodeError) as err:
        raise LirisError(path, f"not valid YAML ({' '.join(str(err).split())})") from None
    if isinstance(config, dict):
        check_schema(config, RUN_CONFIG_SCHEMA, path)
    if not isinstance(config, dict) or "sequence" not in config or "descriptors" not in config:
        raise LirisError(path, "not a liris run config (no 'sequence' or 'descriptors')")
    return config


def _yaml_value(value: Any) -> str:
    return yaml.safe_dump(value, default_flow_style=True, width=10_000).strip().removesuffix(
        "\n...").strip()


def _poses_only(sequence: dict[str, Any]) -> bool:
    """True for a ``liris eval --poses P --loops F`` run: its "sequence" is the pose file."""
    poses = (sequence.get("reader_options") or {}).get("poses")
    return poses is not None and Path(poses).resolve() == Path(sequence["path"]).resolve()


#: loop-source parameter (config.yaml) -> ``liris eval`` parameter name
_LOOP_PARAMS = {"index_base": "loops_index_base", "gap": "loops_gap",
                "keyframe_times": "loops_times", "keyframe_map": "loops_map",
                "time_tolerance_s": "loops_time_tolerance",
                "coverage_tolerance_frames": "loops_coverage_tolerance",
                "posegraph_kernel": "posegraph_kernel", "odometry": "loops_odometry"}


def _loop_sources(sources: list[dict[str, Any]]) -> dict[str, Any]:
    """The ``--loops`` options that rerun a loops run (docs/loops.md)."""
    if not sources:
        return {}
    params = [d.get("params") or {} for d in sources]
    out: dict[str, Any] = {"loop_paths": [p["path"] for p in params]}
    formats = {p.get("format") for p in params}
    if len(formats) == 1 and None not in formats:
        out["loops_format"] = formats.pop()
    for key, name in _LOOP_PARAMS.items():  # one value for every file (as on the command line)
        value = params[0].get(key)
        if value not in (None, ""):
            out[name] = value
    return out


def config_defaults(config: dict[str, Any]) -> dict[str, Any]:
    """``liris eval`` option values (by parameter name) that rerun ``config``."""
    out: dict[str, Any] = {}
    sequence = config.get("sequence") or {}
    if sequence.get("path") and not _poses_only(sequence):
        out["sequence"] = sequence["path"]
    if config.get("protocols"):
        out["protocols"] = [str(p) for p in config["protocols"]]
    builtin = [d for d in config.get("descriptors") or []
               if d.get("preset") not in ("external", "loops")]
    out.update(_loop_sources([d for d in config.get("descriptors") or []
                              if d.get("preset") == "loops"]))
    external = [d for d in config.get("descriptors") or [] if d.get("preset") == "external"]
    if builtin:
        out["descriptor_text"] = ",".join(f"{d['name']}:{d['preset']}" for d in builtin)
        out["params"] = [f"{d['name']}.{key}={_yaml_value(value)}" for d in builtin
                         for key, value in (d.get("params") or {}).items()
                         if key != "odometry"]  # set by --odometry (below)
        sources = {(d.get("params") or {}).get("odometry") for d in builtin} - {None, "gt"}
        if sources and not config.get("odometry"):  # a run from before --odometry
            out["odometry_text"] = sources.pop()
    if config.get("odometry_file"):
        out["odometry_text"] = config["odometry_file"]
    elif config.get("odometry"):
        out["odometry_text"] = config["odometry"]
    if external:
        out["externals"] = [f"{d['name']}={d['params']['path']}" for d in external]
        metrics = {d["params"].get("metric") for d in external} - {None}
        if len(metrics) > 1:
            raise LirisError("config.yaml", f"external descriptors use several metrics "
                                            f"({', '.join(sorted(metrics))}); replay them "
                                            "one at a time")
        if metrics:
            out["external_metric"] = metrics.pop()
    if config.get("sensor"):
        out["sensor"] = config["sensor"]
    convention = config.get("convention") or {}
    base = str(convention.get("preset") or "").split("+")[0]
    if base and base != "custom":  # "<preset>+custom": the preset, then the values below
        out["convention_name"] = base
    if config.get("radius") is not None:
        out["radius"] = config["radius"]
    exclude = config.get("exclude") or {}
    if convention.get("exclude_seconds") is not None:
        out["exclude"] = f"{convention['exclude_seconds']:g}s"
    elif exclude.get("value") is not None:
        out["exclude"] = str(exclude["value"])
    for key in ("distance", "pose_frame", "recall_denominator", "candidates"):
        if config.get(key) is not None:
            out[key] = config[key]
    if config.get("block_pairs") is not None:
        out["block_pairs"] = config["block_pairs"]
    loops = config.get("loop_poses") or {}  # issue 23 (evaluation/loop_poses.py)
    for key, param in (("refine", "refine"), ("gt_pose", "gt_pose"),
                       ("min_inlier_ratio", "min_inlier_ratio"), ("max_rmse_m", "max_rmse_m")):
        if loops.get(key) is not None:
            out[param] = loops[key]
    if loops.get("rr_thresholds"):
        out["rr_thresholds"] = ",".join(f"{v:g}" for v in loops["rr_thresholds"])
    if config.get("seeds"):
        out["seeds_text"] = ",".join(str(s) for s in config["seeds"])
    for key, value in (sequence.get("reader_options") or {}).items():
        if key in READER_PARAMS:
            out[READER_PARAMS[key]] = value
    return out
