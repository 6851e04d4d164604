"""Which folders ``--overwrite`` may replace: only those liris wrote, with nothing added.

``--overwrite`` used to mean "delete whatever is at ``--out``", so
``liris eval S --out S --overwrite`` deleted the input sequence and a results
folder that also held a user's notes lost them. Now every folder liris
publishes (a run, a multi-sequence run, a report) carries a manifest,
:data:`MANIFEST`, listing the files it wrote. A folder is replaceable only
when

* it is absent or empty, or
* it carries a liris manifest of an expected kind, is not a symbolic link,
  and every file in it is listed in that manifest, lies in a nested folder
  whose own manifest vouches for it (a report inside a run), or is a figure
  ``liris plot`` writes into the run's ``figures/`` folder.

Anything else (an input sequence, a home folder, a run someone copied a file
into) is refused before any work starts, naming the first foreign file, and
nothing is touched. :func:`replace_folder` then swaps the new folder in with
renames, so the old one is deleted only once the new one is in place.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Iterable
from pathlib import Path

from lidar_iris_eval.errors import LirisError

#: the file that marks a folder as written by liris
MANIFEST = ".liris-manifest.json"
#: derived files ``liris plot`` adds to a run folder (``RUN/figures/<stem>.<fmt>``)
FIGURE_SUFFIXES = (".png", ".pdf", ".svg")

KINDS = ("run", "multi", "report")


def read_manifest(folder: Path) -> dict | None:
    """The folder's liris manifest, or ``None`` when it has none (or an unreadable one)."""
    path = Path(folder) / MANIFEST
    if path.is_symlink() or not path.is_file():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict) or data.get("written_by") != "liris":
        return None
    if data.get("kind") not in KINDS or not isinstance(data.get("files"), list):
        return None
    return data


def manifest_text(kind: str, files: Iterable[str]) -> str:
    """The manifest for a folder of ``kind`` holding ``files`` (paths relative to it)."""
    if kind not in KINDS:
        raise ValueError(f"unknown folder kind {kind!r}")
    body = {"written_by": "liris", "kind": kind, "files": sorted(set(files))}
    return json.dumps(body, indent=1) + "\n"


def write_manifest(folder: Path, kind: str) -> None:
    """Write the manifest of ``folder`` (about to be published), listing every file in it."""
    folder = Path(folder)
    (folder / MANIFEST).write_text(manifest_text(kind, list_files(folder)), encoding="utf-8")


def list_files(folder: Path) -> list[str]:
    """Every file and link below ``folder`` (relative, ``/``-separated), the manifest excluded."""
    found = []
    for root, dirs, files in os.walk(folder):
        base = Path(root)
        # a link to a folder is listed as an entry, never walked into
        for name in [d for d in dirs if (base / d).is_symlink()]:
            dirs.remove(name)
            files.append(name)
        for name in files:
            rel = (base / name).relative_to(folder).as_posix()
            if rel != MANIFEST:
                found.append(rel)
    return sorted(found)


def check_replaceable(path: str | os.PathLike, kinds: tuple[str, ...], flag: str = "--out") -> None:
    """Raise :class:`LirisError` unless ``--overwrite`` may replace ``path``.

    Parameters
    ----------
    path : the folder the caller would replace.
    kinds : the manifest kinds it may be (``("run",)`` for ``liris eval``).
    flag : how the user named the folder, for the message.
    """
    path = Path(path)
    if path.is_symlink():
        raise LirisError(path, f"{flag} is a symbolic link; --overwrite does not replace links")
    if not path.exists():
        return
    if not path.is_dir():
        raise LirisError(path, "exists and is not a directory")
    if not any(path.iterdir()):
        return
    manifest = read_manifest(path)
    if manifest is None:
        raise LirisError(path, f"not a folder liris wrote (no {MANIFEST}): --overwrite only "
                               "replaces liris's own results; choose another "
                               f"{flag} or remove it yourself")
    if manifest["kind"] not in kinds:
        raise LirisError(path, f"is a liris {manifest['kind']} folder, not a "
                               f"{' or '.join(kinds)} folder; not replaced")
    foreign = first_foreign_file(path, manifest)
    if foreign is not None:
        raise LirisError(path, f"holds {foreign}, which liris did not write; not replaced "
                               f"(move it away or choose another {flag})")


def first_foreign_file(folder: Path, manifest: dict) -> str | None:
    """The first file below ``folder`` that neither its manifest nor a nested one lists."""
    listed = set(manifest["files"])
    nested: dict[str, str | None] = {}  # nested folder with a manifest -> its first foreign file
    for rel in list_files(folder):
        if rel in listed or _is_run_figure(folder, rel, manifest["kind"]):
            continue
        owner = _nested_owner(folder, rel, nested)
        if owner is None:
            return rel
        if nested[owner] is not None:
            return f"{owner}/{nested[owner]}"
    return None


def _is_run_figure(folder: Path, rel: str, kind: str) -> bool:
    parts = rel.split("/")
    return (kind == "run" and len(parts) == 2 and parts[0] == "figures"
            and parts[1].endswith(FIGURE_SUFFIXES) and not (folder / rel).is_symlink())


def _nested_owner(folder: Path, rel: str, nested: dict[str, str | None]) -> str | None:
    """The outermost folder above ``rel`` with a liris manifest of its own (checked once)."""
    parts = rel.split("/")
    for depth in range(1, len(parts)):
        sub = "/".join(parts[:depth])
        if sub in nested:
            return sub
        if (folder / sub).is_symlink():
            return None
        manifest = read_manifest(folder / sub)
        if manifest is not None:
            nested[sub] = first_foreign_file(folder / sub, manifest)
            return sub
    return None


def replace_folder(new: Path, target: Path) -> Path:
    """Move the finished folder ``new`` to ``target``, replacing a checked old one.

    The old folder is renamed aside first and deleted only after ``new`` is in
    place, so a failure in between leaves one complete folder or the other.
    The caller has checked ``target`` with :func:`check_replaceable`.
    """
    new, target = Path(new), Path(target)
    old = None
    if target.exists():
        old = target.parent / f".{target.name}.old-{os.getpid()}"
        shutil.rmtree(old, ignore_errors=True)
        os.rename(target, old)
    try:
        os.rename(new, target)
    except OSError:
        if old is not None:
            os.rename(old, target)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    return target


def check_new_files(paths: Iterable[str | os.PathLike], overwrite: bool, flag: str,
                    inputs: Iterable[str | os.PathLike] = ()) -> None:
    """Refuse to write single files over existing ones unless ``overwrite``.

    For files such as ``--export-loops loops.g2o`` or ``compare --plot pr.png``:
    an existing file is replaced only when the user asked for it, a folder or
    a link in the way never is, and a file inside one of the ``inputs`` (the
    sequence being evaluated) is never replaced at all, ``overwrite`` or not.
    Checked before any work starts.
    """
    roots = [Path(p).resolve() for p in inputs]
    for path in map(Path, paths):
        if not (path.exists() or path.is_symlink()):
            continue
        if path.is_symlink() or not path.is_file():
            raise LirisError(path, f"{flag}: exists and is not a regular file; not replaced")
        if not overwrite:
            raise LirisError(path, f"{flag}: file already exists; pass --overwrite to replace it")
        resolved = path.resolve()
        for root in roots:
            if resolved == root or root in resolved.parents:
                raise LirisError(path, f"{flag}: is part of the input {root}; never replaced")
