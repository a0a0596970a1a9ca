"""Outputs the pipeline replaces whole, and only when it wrote them: the report's ``REPORT.md``,
``summary.csv``, ``figures/`` and ``export/`` under ``paths.results``; ``pgnn-ff export``'s
packages under ``--out`` (issue 24, item 2: nothing of the user's is lost).

``.pgnn-owned.json`` in the output folder lists every file the pipeline wrote there with its
SHA-256, signed with this user's cache key (an edited record vouches for nothing).  Before any
work, a file under a target that is not listed, or that changed since it was written, is the
user's (unless git tracks it unmodified: git restores it): the job is refused, naming it, and
nothing is deleted.  Everything else in the folder is never touched.  Imports nothing from the rest
of the pipeline but its errors, the safe writer and the cache's ROOT and signature.
"""
from __future__ import annotations

import hashlib
import hmac
import json
import subprocess
from pathlib import Path
from typing import Iterable

from pipeline.atomic import read_nofollow, replace_file
from pipeline.cache import ROOT, _signature, cache_key_file
from pipeline.errors import ConfigError

MANIFEST = ".pgnn-owned.json"
#: the source tree: outputs never go inside it (a stale file there would be imported or committed)
SOURCE = tuple(ROOT / d for d in ("pipeline", "stages", "conf", "tests", "hydra_plugins", "benchmarks"))


def inside_source(path: Path) -> bool:
    """True if ``path`` (links resolved) is the repository's top folder, a folder of the source tree
    or inside one."""
    p = Path(path).resolve()
    return p == ROOT or any(p == s or s in p.parents for s in SOURCE + (ROOT / ".git",))


def unsafe_place(path: Path) -> str | None:
    """Why ``path`` (links resolved) must not receive outputs: the file system's root, the home
    folder, or the source tree; None if it may."""
    p = Path(path).resolve()
    if p == Path(p.anchor):
        return "the file system's root"
    if p == Path.home().resolve():
        return "the home folder"
    if inside_source(p):
        return "inside the source tree"
    return None


def _sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def _signed(files: dict) -> str:
    """The record's signature: HMAC-SHA256 with this user's cache key over its canonical JSON (issue 51
    item 5: an unsigned record let whoever can write the folder list a user's file, which was then deleted)."""
    return _signature(b"pgnn-owned", json.dumps(files, sort_keys=True).encode())


def _listed(root: Path) -> dict[str, str]:
    """The record's files, if it is signed with this user's cache key; else nothing (an edited, copied or
    older record vouches for nothing: its files are the user's, or git's, see :func:`_committed`)."""
    try:
        listed = json.loads(read_nofollow(root / MANIFEST))
    except (OSError, ValueError):
        return {}
    if not (isinstance(listed, dict) and isinstance(listed.get("files"), dict)
            and isinstance(listed.get("signature"), str)):
        return {}
    ok = hmac.compare_digest(listed["signature"].encode(), _signed(listed["files"]).encode())
    return listed["files"] if ok else {}


def _committed(root: Path) -> dict[str, str]:
    """Files under ``root`` that this repository's git tracks, with their blob hashes (``git ls-files -s``):
    such a file, unmodified, is never lost when replaced (git restores it), so it counts as the pipeline's
    (a fresh clone's committed ``results/``, whose record is signed with another user's key)."""
    p = Path(root).resolve()
    if ROOT not in p.parents or not (ROOT / ".git").exists():
        return {}
    try:
        out = subprocess.run(["git", "-C", str(ROOT), "ls-files", "-s", "-z", "--", str(p)], capture_output=True,
                             timeout=30, check=True).stdout.decode(errors="replace")
    except (OSError, subprocess.SubprocessError):
        return {}
    got = {}
    for line in filter(None, out.split("\0")):
        meta, path = line.split("\t", 1)
        got[(ROOT / path).relative_to(p).as_posix()] = meta.split()[1]
    return got


def _git_blob(f: Path) -> str:
    data = read_nofollow(f)
    return hashlib.sha1(b"blob %d\0" % len(data) + data).hexdigest()   # git's object id of a file


def _files(root: Path, targets: Iterable[str]) -> list[Path]:
    out = []
    for t in targets:
        p = root / t
        if p.is_dir() and not p.is_symlink():
            out += sorted(f for f in p.rglob("*") if not f.is_dir() or f.is_symlink())
        elif p.exists() or p.is_symlink():
            out.append(p)
    return out


def foreign(root: Path, targets: Iterable[str]) -> list[str]:
    """Files under ``root/<target>`` (a file or a folder) the pipeline did not write, or that were
    changed since (paths relative to ``root``)."""
    listed, git = _listed(root), None
    out = []
    for f in _files(root, targets):
        rel = f.relative_to(root).as_posix()
        if f.is_symlink() or not f.is_file():
            out.append(rel)
        elif not _accepted(listed.get(rel), f):
            git = _committed(root) if git is None else git
            if git.get(rel) != _git_blob(f):
                out.append(rel)
    return out


def _accepted(entry, f: Path) -> bool:
    """``entry``: the hash written, or (between :func:`allow` and :func:`record`) a list of hashes."""
    return entry is not None and _sha(f) in ([entry] if isinstance(entry, str) else entry)


def refuse_foreign(root: Path, targets: Iterable[str], option: str) -> None:
    """Raise :class:`ConfigError` (before any work) if replacing ``targets`` under ``root`` would
    delete or overwrite a file that is not the pipeline's; ``option`` names the setting to change."""
    root = Path(root)
    why = unsafe_place(root)
    if why:
        raise ConfigError(f"{option}={root} is {why}; write outputs to a folder of their own")
    if root.exists() and not root.is_dir():
        raise ConfigError(f"{option}={root} is a file, not a folder; give a folder")
    bad = foreign(root, targets)
    if bad:
        more = f" and {len(bad) - 5} more" if len(bad) > 5 else ""
        record = root / MANIFEST
        unsigned = (f" ({MANIFEST} there is not signed with your cache key {cache_key_file()}: written by another "
                    "user or an older version, or edited; it vouches for nothing: outputs of an older version are "
                    "removed by hand or restored with git checkout)"
                    if (record.exists() or record.is_symlink()) and not _listed(root) else "")
        raise ConfigError(f"{option}={root} holds file(s) this pipeline did not write or that were edited since "
                          f"({', '.join(bad[:5])}{more}){unsigned}; they would be replaced. Move them elsewhere, or "
                          f"set {option} to a folder of its own")


def record(root: Path, targets: Iterable[str]) -> None:
    """After writing ``targets`` under ``root``: list each of their files with its hash (entries of
    other targets kept, those of removed files dropped); the list is replaced atomically."""
    root = Path(root)
    targets = list(targets)
    listed = {k: v for k, v in _listed(root).items()
              if not any(k == t or k.startswith(f"{t}/") for t in targets)}
    listed |= {f.relative_to(root).as_posix(): _sha(f) for f in _files(root, targets) if f.is_file()}
    _save(root, listed)


def allow(root: Path, rel: str, source: Path | bytes) -> None:
    """Before ``source`` (a folder, or a file's bytes) is swapped in as ``root/rel``: list its files'
    hashes beside the current ones, so a job stopped between the swap and :func:`record` leaves outputs
    the next job still knows as the pipeline's (not as a user's edit)."""
    root = Path(root)
    listed = _listed(root)
    if isinstance(source, bytes):
        shas = {rel: hashlib.sha256(source).hexdigest()}
    else:
        shas = {f"{rel}/{f.relative_to(source).as_posix()}": _sha(f)
                for f in sorted(Path(source).rglob("*")) if f.is_file()}
    for key, sha in shas.items():
        old = listed.get(key) or []
        listed[key] = sorted(set([old] if isinstance(old, str) else old) | {sha})
    _save(root, listed)


def _save(root: Path, listed: dict) -> None:
    files = dict(sorted(listed.items()))
    replace_file(root / MANIFEST, json.dumps({"files": files, "signature": _signed(files)}, indent=0))
