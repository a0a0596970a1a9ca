"""The stage cache's low level: temporary names, stale-temporary cleanup, per-entry locks, and the
signed entries (HMAC-SHA256 with this user's cache key; an unsigned or altered entry is never
unpickled).  Imports nothing from the rest of the pipeline but :mod:`pipeline.atomic` (:mod:`pipeline.runner`
and :mod:`pipeline.tracking` both use it)."""
from __future__ import annotations

import hashlib
import hmac
import json
import os
import pickle
import re
import shutil
import socket
import stat
import sys
import time
from pathlib import Path
from typing import Any

from filelock import FileLock

from pipeline.atomic import read_nofollow, replace_file, umask

ROOT = Path(__file__).resolve().parent.parent


def cache_dir(cfg) -> Path:
    """The stage cache: ``paths.cache``, else ``$PIPELINE_CACHE``, else ``<repo>/.cache``."""
    p = cfg.get("paths", {}).get("cache") or os.environ.get("PIPELINE_CACHE") or ROOT / ".cache"
    return Path(p)

#: this machine in temporary names: a shared (cluster) cache is cleaned only of this machine's leftovers
HOST = re.sub(r"[^A-Za-z0-9.]", "_", socket.gethostname()) or "host"
_TMP = re.compile(r"^\.tmp-[0-9a-f]+-(?P<host>.+)-(?P<pid>\d+)-\d+$")


def _tmp_name(key: str) -> str:
    """A stage's temporary directory: key, this machine, this process (a stale one is recognisable)."""
    return f".tmp-{key}-{HOST}-{os.getpid()}-{time.time_ns()}"


def pid_alive(pid: int) -> bool:
    """True if process ``pid`` exists on this machine (a reused pid errs on the safe side)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_temporaries(store: Path) -> list[Path]:
    """Remove the temporary stage directories left by dead processes of this machine (a SIGKILL
    or an OOM kill gives no chance to clean up); others' are left alone."""
    removed = []
    if not store.is_dir():
        return removed
    for stage in store.iterdir():
        if not stage.is_dir() or stage.name.startswith("."):
            continue
        for d in stage.glob(".tmp-*"):
            m = _TMP.match(d.name)
            if m and m["host"] == HOST and not pid_alive(int(m["pid"])):
                shutil.rmtree(d, ignore_errors=True)
                removed.append(d)
    return removed


def private_dir(tmp: Path) -> None:
    """A new temporary entry folder only this user can enter (mode 0700; :func:`_write_signed` opens it to
    the usual mode once whole): in a cache a group shares, no one else writes into it or plants a link
    there for the stage to write through while it fills it (issue 51)."""
    tmp.parent.mkdir(parents=True, exist_ok=True)
    tmp.mkdir(mode=0o700)


def _locked(final: Path) -> FileLock:
    """The lock of one cache entry (``<cache>/.locks/<stage>-<key>.lock``): held while it is computed."""
    locks = final.parent.parent / ".locks"
    locks.mkdir(parents=True, exist_ok=True)
    lock = locks / f"{final.parent.name}-{final.name}.lock"
    if lock.is_symlink():   # never open (and truncate) whatever a planted link points at
        lock.unlink()
    return FileLock(str(lock))


class UntrustedCache(Exception):
    """A cache entry not signed with this machine's cache key (written elsewhere, or altered)."""


class StaleCache(Exception):
    """A signed cache entry whose pickle names a class the code no longer has there (moved)."""


class BadKey(ValueError):
    """The signing key file cannot be used (the runner reports it as bad input, before any work)."""


class ShortKey(BadKey):
    """The signing key file holds fewer than KEY_MIN_BYTES bytes."""


_KEYS: dict[Path, bytes] = {}   # signing key per key file, read once


def cache_key_file() -> Path:
    """The secret that signs this user's cache entries (``$PIPELINE_CACHE_KEY_FILE``, else
    ``~/.config/pgnn-feedforward/cache.key``; created with mode 600 on first use)."""
    return Path(os.environ.get("PIPELINE_CACHE_KEY_FILE")
                or Path.home() / ".config" / "pgnn-feedforward" / "cache.key")


#: shortest signing key accepted (HMAC-SHA256's block of security: 32 random bytes)
KEY_MIN_BYTES = 32


def _signing_key() -> bytes:
    """This user's signing key, created on first use: 32 random bytes written to a temporary file
    and linked into place (never a partial key file, even on a full disk); a key shorter than
    32 bytes is refused (an empty key would let anyone sign a forged entry)."""
    path = cache_key_file()
    if path not in _KEYS:
        path.parent.mkdir(parents=True, exist_ok=True)
        if not path.exists():
            tmp = path.with_name(f".{path.name}.{HOST}-{os.getpid()}-{time.time_ns()}")
            try:
                fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
                with os.fdopen(fd, "wb") as f:
                    f.write(os.urandom(KEY_MIN_BYTES))
                    f.flush()
                    os.fsync(f.fileno())
                try:
                    os.link(tmp, path)          # atomic and exclusive: another process's key wins
                except FileExistsError:
                    pass
            except OSError as exc:               # a full disk: name the key, not "an unnamed file"
                exc.filename = exc.filename or str(path)
                raise
            finally:
                tmp.unlink(missing_ok=True)
        key = _read_key(path)
        _KEYS[path] = key
    return _KEYS[path]


def _read_key(path: Path) -> bytes:
    """The key file's bytes, from one open descriptor, refused (one line naming the fix) unless it is a
    regular file of this user, not writable by group or others, of exactly KEY_MIN_BYTES bytes that are
    not one byte repeated (issue 51 item 3: /etc/passwd, a device, or 32 zero bytes of mode 666 were
    accepted, and a forgery signed with them ran)."""
    fix = ("delete it (a new one is made; entries signed with the old one are recomputed) or point "
           "PIPELINE_CACHE_KEY_FILE at a file of your own")
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))   # a fifo must not block
    except FileNotFoundError:   # a link to nothing (exists() was False, the new key could not be linked)
        raise BadKey(f"the cache signing key {path} is a link to a missing file: {fix}") from None
    st = os.fstat(fd)
    if not stat.S_ISREG(st.st_mode):
        os.close(fd)
        raise BadKey(f"the cache signing key {path} is not a plain file: {fix}")
    with os.fdopen(fd, "rb") as f:
        if hasattr(os, "geteuid") and st.st_uid != os.geteuid():
            raise BadKey(f"the cache signing key {path} belongs to uid {st.st_uid}, not to you (uid {os.geteuid()}): "
                         f"anyone who can write it can forge entries; copy it to a file of your own (cp {path} "
                         f"~/my.key && chmod 600 ~/my.key) and point PIPELINE_CACHE_KEY_FILE at it")
        if st.st_mode & 0o022:
            who = "others" if st.st_mode & 0o002 else "its group"
            raise BadKey(f"the cache signing key {path} can be written by {who}"
                         f" (mode {stat.S_IMODE(st.st_mode):o}): whoever changes it can forge entries; "
                         f"run chmod 600 {path}")
        key = f.read(KEY_MIN_BYTES + 1)
    if len(key) < KEY_MIN_BYTES:
        raise ShortKey(f"the cache signing key {path} holds {len(key)} bytes, fewer than {KEY_MIN_BYTES}: "
                       "it cannot be trusted. Delete it (a new one is made; entries signed with the old one "
                       "are recomputed)")
    if len(key) > KEY_MIN_BYTES:
        raise BadKey(f"the cache signing key {path} holds more than {KEY_MIN_BYTES} bytes: it is not a key this "
                     f"pipeline made (a key is {KEY_MIN_BYTES} random bytes); {fix}")
    if len(set(key)) == 1:
        raise BadKey(f"the cache signing key {path} is one byte repeated ({key[:1]!r} x {KEY_MIN_BYTES}), not a "
                     f"secret; {fix}")
    return key


def _signature(*blobs: bytes) -> str:
    mac = hmac.new(_signing_key(), digestmod=hashlib.sha256)
    for b in blobs:
        mac.update(hashlib.sha256(b).digest())
    return mac.hexdigest()


_SIGNED = ("result.pkl", "record.json", "signature")


def _tree(entry: Path) -> dict[str, str]:
    """Every other file of the entry (exported C, laws, datasets, figures: what a later stage, the
    tracking store or ``pgnn-ff export`` trusts): relative path -> SHA-256, in sorted order.  A link,
    or anything that is neither file nor folder, cannot be trusted (it may point anywhere)."""
    out = {}
    for p in sorted(entry.rglob("*")):
        rel = p.relative_to(entry).as_posix()
        if p.is_symlink() or not (p.is_file() or p.is_dir()):
            raise UntrustedCache(f"{entry} holds {rel}, which is not a plain file or folder")
        if p.is_file() and rel not in _SIGNED:
            out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def _blobs(entry: Path, final: Path, payload: bytes, rec: bytes | None, tree: dict[str, str]) -> list[bytes]:
    """What the signature covers: where the entry belongs (``<stage>/<key>``: a signed entry copied
    under another config's key fails), its pickle, its record and every other file it holds (``tree``,
    as sorted ``<relative path> <sha256>`` lines)."""
    lines = "\n".join(f"{rel} {sha}" for rel, sha in tree.items()).encode()
    return [f"{final.parent.name}/{final.name}".encode(), payload] + ([rec] if rec is not None else []) + \
        ([lines] if lines else [])


def _write_signed(entry: Path, result, record: dict | None = None, final: Path | None = None) -> None:
    """``result.pkl`` (+ ``record.json``) and ``signature``: HMAC-SHA256 with the cache key of the
    place ``final`` the entry is renamed to (default: ``entry``), both files and every other file the
    entry holds (written last, once the entry is complete)."""
    payload = pickle.dumps(result, protocol=pickle.HIGHEST_PROTOCOL)
    (entry / "result.pkl").write_bytes(payload)
    rec = None
    if record is not None:
        rec = json.dumps(record, indent=1).encode()
        (entry / "record.json").write_bytes(rec)
    (entry / "signature").write_text(_signature(*_blobs(entry, final or entry, payload, rec, _tree(entry))))
    os.chmod(entry, 0o777 & ~umask())   # made private (0700) while it was filled: readable as usual once whole


def _verified(entry: Path) -> tuple[bytes, bytes | None, dict[str, str]]:
    """The entry's pickle, record and file hashes, once its signature checked out: over its place, the
    pickle, the record and every other file of the entry (a file added, removed or altered, or the entry
    moved under another key, fails).  A signature file that is not text is a signature that fails."""
    payload = (entry / "result.pkl").read_bytes()
    rec = (entry / "record.json").read_bytes() if (entry / "record.json").exists() else None
    tree = _tree(entry)
    sig = entry / "signature"
    got = sig.read_bytes().strip() if sig.exists() else b""
    if not hmac.compare_digest(got, _signature(*_blobs(entry, entry, payload, rec, tree)).encode()):
        raise UntrustedCache(f"{entry} is not signed with this machine's cache key ({cache_key_file()}), "
                             "or a file in it was altered, added or removed, or it was moved from another key")
    return payload, rec, tree


def _read_signed(entry: Path) -> tuple[Any, dict | None]:
    """The entry's result (and record), unpickled only after its signature checked out (:func:`_verified`)."""
    payload, rec, _ = _verified(entry)
    try:
        result = pickle.loads(payload)
    except (AttributeError, ImportError) as exc:   # written by an older layout of the code (a class moved)
        raise StaleCache(f"{entry} holds a class this code no longer has where it was ({exc})") from None
    return result, (json.loads(rec) if rec is not None else None)


def copy_signed(entry: Path, folder: str, dest: Path) -> list[str]:
    """Copy ``entry/folder`` to ``dest`` (a new folder), only what the entry's signature covers: each file
    is read once from a descriptor opened without following a link, and its bytes are written only if
    their SHA-256 is the signed one (issue 51 item 2: no check-then-copy, so a file swapped in after the
    check is never shipped).  Returns the files copied (relative to ``folder``); raises
    :class:`UntrustedCache` for an unsigned or altered entry, or a file changed while it was copied."""
    _, _, tree = _verified(entry)
    prefix = f"{folder.strip('/')}/"
    copied = []
    for rel, sha in tree.items():
        if not rel.startswith(prefix):
            continue
        try:
            blob = read_nofollow(entry / rel)
        except OSError as exc:
            raise UntrustedCache(f"{entry / rel} cannot be read as a plain file ({exc})") from None
        if hashlib.sha256(blob).hexdigest() != sha:
            raise UntrustedCache(f"{entry / rel} changed after its entry's signature was checked")
        target = dest / rel[len(prefix):]
        target.parent.mkdir(parents=True, exist_ok=True)
        replace_file(target, blob)
        copied.append(rel[len(prefix):])
    return copied


def _load_trusted(entry: Path) -> tuple[Any, dict | None] | None:
    """The entry's (result, record); None when there is no entry, or after moving an untrusted or
    incomplete one (a file missing: a copy cut short, a hand edit) out of the way, never loaded, so
    that it is recomputed."""
    if not entry.exists() and not entry.is_symlink():
        return None
    try:
        if entry.is_symlink() or not entry.is_dir():
            raise UntrustedCache(f"{entry} is not a folder")
        return _read_signed(entry)
    except (UntrustedCache, StaleCache, FileNotFoundError, NotADirectoryError, IsADirectoryError) as why:
        aside = entry.with_name(f".untrusted-{entry.name}-{time.time_ns()}")
        os.rename(entry, aside)
        print(f"warning: {why}; not loaded (moved to {aside.name}), recomputing", file=sys.stderr, flush=True)
        prune_untrusted(entry.parent)
        return None


#: entries set aside as untrusted kept per stage folder for inspection (the newest); older ones are deleted
KEEP_UNTRUSTED = 3
_UNTRUSTED = re.compile(r"^\.untrusted-.+-(?P<ns>\d+)$")


def prune_untrusted(stage: Path) -> list[Path]:
    """Delete all but the :data:`KEEP_UNTRUSTED` newest ``.untrusted-*`` folders of a stage folder (by the
    time in their name): they grew without bound (19 after 7 runs, issue 51). Returns those deleted."""
    aside = sorted((p for p in stage.iterdir() if _UNTRUSTED.match(p.name)),
                   key=lambda p: int(_UNTRUSTED.match(p.name)["ns"]), reverse=True)
    for p in aside[KEEP_UNTRUSTED:]:
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
    return aside[KEEP_UNTRUSTED:]
