"""Opt-in cross-process compilation cache: JAX's own persistent cache in a checked directory.

Nothing here runs on ``import jaxlag``: JAX's configuration is the user's. A research script that
wants its second run to skip XLA compilation calls `enable_compilation_cache` once, before
its first computation::

    import jaxlag as jl
    jl.enable_compilation_cache()          # $XDG_CACHE_HOME/jaxlag/jax, default ~/.cache/jaxlag/jax

Whoever can write a cache entry chooses the code the next run executes, so the directory is checked
the way sshd's ``StrictModes`` checks ``~/.ssh`` before it trusts the keys in it:

* every directory from ``/`` down to the cache directory is a real directory (not a symlink),
  owned by the user (or root, for the ancestors) and not group- or world-writable (a root-owned
  sticky ``/tmp`` is fine): nobody else can rename, replace or add anything along the path;
* the cache directory is created with mode 0700, whatever the umask. A directory that grants
  group and others nothing is *private*: nobody but the user (and root) can open a path inside
  it, so the mode of an entry in it does not matter. This is what keeps the user's own cache
  usable under any umask: JAX writes its entries with the mode the umask leaves (0664 under umask
  002, 0666 under 000), and inside a private directory they are as unreachable as 0600 ones. The
  entries found there are set to 0600 (the user's alone), so that they stay private if the
  directory is ever opened up. In a directory that others can enter (0755, say, made by the
  user), an entry that group or others can write is refused, with the fix;
* every entry is a regular file (no symlink, FIFO, device or sub-directory), owned by the user,
  with no second hard link (a path outside the directory that others might write it through), and
  no larger than ``max_entry_bytes``;
* ``HOME`` and ``XDG_CACHE_HOME`` are used only when they are absolute paths (the XDG base
  directory specification says to ignore relative ones); an empty or relative ``HOME`` with no
  usable ``XDG_CACHE_HOME`` is an error, not ``/.cache``.

An unsafe directory is refused with `UnsafeCacheDirectory`, whose message says which path and
why; nothing is changed then. Once the directory is accepted, what killed writers left is
repaired: stale temporaries (``*.tmp``/``*.partial`` files older than an hour) are removed, and so
is every entry that fails to decompress the way JAX reads it (zlib, or zstd where JAX uses it: a
file truncated by a writer killed mid-write), with one warning, so that the program is compiled
and stored again (JAX itself never replaces an entry that exists, and would warn about it on
every run). Only the entries written since the last call are read: the modification time of
``.jaxlag-verified`` in the directory records when that was, so a call costs a ``stat`` per entry,
not a read. jaxlag stores no Python objects and loads no executables of its own: JAX writes and
reads the entries through its own file cache.
"""

import contextlib
import importlib
import os
import stat
import time
import warnings
import zlib
from collections.abc import Callable
from pathlib import Path

import jax

__all__ = ["UnsafeCacheDirectory", "default_cache_directory", "enable_compilation_cache"]

#: Entries larger than this are refused (JAX's largest jaxlag program is a few MB).
DEFAULT_MAX_ENTRY_BYTES = 256 * 2**20
_STALE_SECONDS = 3600.0
_TEMPORARY_SUFFIXES = (".tmp", ".partial")
_ENTRY_SUFFIX = "-cache"  # JAX's file cache stores the program of key K as "K-cache"
_VERIFIED = ".jaxlag-verified"  # its modification time: when the entries were last read
_CLOCK_SLACK_NS = 2 * 10**9  # file systems with 2 s timestamps (FAT)
_ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"


class UnsafeCacheDirectory(RuntimeError):
    """The compilation cache directory could be written by someone else, or is not a plain
    directory of regular files: JAX's cache is not turned on."""


def _absolute_env(name: str) -> Path | None:
    """The environment variable as an absolute path, or None if unset, empty or relative."""
    value = os.environ.get(name, "")
    if not value or not os.path.isabs(value):
        return None
    return Path(value)


def default_cache_directory() -> Path:
    """``$XDG_CACHE_HOME/jaxlag/jax``, or ``$HOME/.cache/jaxlag/jax``; only absolute values of
    those variables are used.

    Raises `UnsafeCacheDirectory` when neither is an absolute path."""
    base = _absolute_env("XDG_CACHE_HOME")
    if base is None:
        home = _absolute_env("HOME")
        if home is None:
            raise UnsafeCacheDirectory(
                "Neither XDG_CACHE_HOME nor HOME is an absolute path "
                f"(XDG_CACHE_HOME={os.environ.get('XDG_CACHE_HOME')!r}, "
                f"HOME={os.environ.get('HOME')!r}); pass `path=` explicitly."
            )
        base = home / ".cache"
    return base / "jaxlag" / "jax"


def _refuse(path: Path, why: str) -> UnsafeCacheDirectory:
    return UnsafeCacheDirectory(f"Refusing the compilation cache at {str(path)!r}: {why}.")


def _check_directory(path: Path, uid: int, *, allow_root_owner: bool) -> None:
    """``path`` is a real directory (not a symlink), owned by ``uid`` (or root where allowed),
    and not writable by group or others. A root-owned sticky ancestor such as ``/tmp`` is
    accepted: its sticky bit keeps other users from renaming or removing what you own in it."""
    info = os.lstat(path)
    if stat.S_ISLNK(info.st_mode):
        raise _refuse(path, "it is a symbolic link")
    if not stat.S_ISDIR(info.st_mode):
        raise _refuse(path, "it is not a directory")
    owners = (uid, 0) if allow_root_owner else (uid,)
    if info.st_uid not in owners:
        raise _refuse(path, f"it is owned by uid {info.st_uid}, not by you (uid {uid})")
    sticky_system = allow_root_owner and info.st_uid == 0 and info.st_mode & stat.S_ISVTX
    if info.st_mode & (stat.S_IWGRP | stat.S_IWOTH) and not sticky_system:
        raise _refuse(path, f"it is writable by group or others (mode {stat.S_IMODE(info.st_mode):o})")


def _is_private(info: os.stat_result) -> bool:
    """No permission at all for group or others: only the owner (and root) can open paths inside."""
    return stat.S_IMODE(info.st_mode) & 0o077 == 0


def _check_entry(where: Path, info: os.stat_result, uid: int, max_entry_bytes: int, reachable: str | None):
    """One entry: a regular file of the user's with one link and of bounded size; if others can
    enter the directory (``reachable``: its mode), not writable by group or others."""
    if not stat.S_ISREG(info.st_mode):
        kind = "a symbolic link" if stat.S_ISLNK(info.st_mode) else "not a regular file"
        raise _refuse(where, f"the cache entry is {kind}")
    if info.st_uid != uid:
        raise _refuse(where, f"the cache entry is owned by uid {info.st_uid}, not by you")
    if info.st_nlink != 1:
        raise _refuse(where, f"the cache entry has {info.st_nlink} hard links (another path could write it)")
    if reachable is not None and info.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        raise _refuse(
            where,
            f"the cache entry is writable by group or others, who can enter its directory (mode "
            f"{reachable}); remove the entry and make the directory private (chmod 700)",
        )
    stale = where.name.endswith(_TEMPORARY_SUFFIXES) and time.time() - info.st_mtime > _STALE_SECONDS
    if info.st_size > max_entry_bytes and not stale:
        raise _refuse(
            where, f"the cache entry has {info.st_size} bytes, more than max_entry_bytes={max_entry_bytes}"
        )


def _check_entries(path: Path, uid: int, max_entry_bytes: int) -> list[tuple[Path, os.stat_result]]:
    """Every entry checked (`_check_entry`), before anything is changed; returns them."""
    info = os.lstat(path)
    reachable = None if _is_private(info) else f"{stat.S_IMODE(info.st_mode):o}"
    entries = []
    with os.scandir(path) as found:
        for entry in found:
            where, entry_info = path / entry.name, entry.stat(follow_symlinks=False)
            _check_entry(where, entry_info, uid, max_entry_bytes, reachable)
            entries.append((where, entry_info))
    return entries


def _zstd_decompress() -> Callable[[bytes], bytes] | None:
    """The zstd decompressor JAX uses where it compresses with zstd (Python 3.14's
    ``compression.zstd``, else the ``zstandard`` package), or None when neither is installed."""
    for name in ("compression.zstd", "zstandard"):
        try:
            module = importlib.import_module(name)
        except ImportError:
            continue
        return module.decompress if name == "compression.zstd" else module.ZstdDecompressor().decompress
    return None


def _damaged(where: Path) -> bool:
    """Whether a JAX cache entry fails to decompress as JAX reads it (a zlib stream, or a zstd
    frame where JAX has zstd). An empty entry is damaged; one in a format not known here is left
    to JAX."""
    fd = os.open(where, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    with os.fdopen(fd, "rb") as file:
        if not stat.S_ISREG(os.fstat(fd).st_mode):  # swapped since it was checked
            return False
        data = file.read()
    if len(data) < 2:
        return True  # the writer was killed before its first bytes
    if data[:4] == _ZSTD_MAGIC:
        decompress = _zstd_decompress()
        if decompress is None:  # written where JAX had zstd; this JAX cannot read it either
            return False
    elif data[0] & 0x0F == 8 and (data[0] << 8 | data[1]) % 31 == 0:  # a zlib header
        decompress = zlib.decompress
    else:
        return False
    try:
        decompress(data)
    except Exception:  # noqa: BLE001 - zlib.error, zstd errors: what JAX would warn about
        return True
    return False


def _last_verified_ns(path: Path) -> int:
    try:
        return os.lstat(path / _VERIFIED).st_mtime_ns
    except FileNotFoundError:
        return 0


def _mark_verified(path: Path, when_ns: int) -> None:
    marker = path / _VERIFIED
    os.close(os.open(marker, os.O_WRONLY | os.O_CREAT | os.O_NOFOLLOW, 0o600))
    os.utime(marker, ns=(when_ns, when_ns))


def _repair_entries(path: Path, entries: list[tuple[Path, os.stat_result]]) -> None:
    """In an accepted directory: stale temporaries removed, entries set to 0600, and the entries
    written since the last call that fail to decompress removed (one warning names them)."""
    started_ns = time.time_ns()
    since_ns = _last_verified_ns(path) - _CLOCK_SLACK_NS  # coarse file-system timestamps
    damaged = []
    for where, info in entries:
        # Best effort: an entry JAX's LRU eviction removed meanwhile, or a read-only file system,
        # leaves that entry as it is (in the private directory it is safe whatever its mode).
        with contextlib.suppress(OSError):
            if where.name.endswith(_TEMPORARY_SUFFIXES):
                if time.time() - info.st_mtime > _STALE_SECONDS:
                    os.unlink(where)
                continue
            if where.name.endswith(_ENTRY_SUFFIX) and info.st_mtime_ns >= since_ns and _damaged(where):
                os.unlink(where)
                damaged.append(where.name)
                continue
            if stat.S_IMODE(info.st_mode) & 0o077:
                os.chmod(where, 0o600)  # a regular file, just checked
    with contextlib.suppress(OSError):  # not recorded: the next call reads them again
        _mark_verified(path, started_ns)
    if damaged:
        warnings.warn(
            f"Removed {len(damaged)} damaged compilation cache entries from {str(path)!r} (truncated "
            f"or corrupt, e.g. by a writer killed mid-write): {', '.join(damaged)}. JAX compiles "
            "and stores them again.",
            RuntimeWarning,
            stacklevel=4,  # enable_compilation_cache's caller
        )


def checked_cache_directory(
    path: str | os.PathLike | None = None, *, max_entry_bytes: int = DEFAULT_MAX_ENTRY_BYTES
) -> Path:
    """Create (mode 0700) or check the cache directory and return its absolute path; see the
    module docstring for the rules. Raises `UnsafeCacheDirectory`."""
    directory = default_cache_directory() if path is None else Path(path)
    if not directory.is_absolute():
        directory = Path.cwd() / directory
    directory = Path(os.path.normpath(directory))
    uid = os.getuid()
    # Every existing ancestor must be safe: the user's own, or a root-owned system directory
    # (/, /home, a sticky /tmp) that others cannot use to swap what lies below.
    parts = directory.parents[::-1]  # "/" first
    for ancestor in parts:
        if ancestor.exists() or ancestor.is_symlink():
            _check_directory(ancestor, uid, allow_root_owner=True)
    for missing in [*parts, directory]:
        if not missing.exists() and not missing.is_symlink():
            os.mkdir(missing, 0o700)
            os.chmod(missing, 0o700)  # the umask may remove bits; be exact
    _check_directory(directory, uid, allow_root_owner=False)
    _repair_entries(directory, _check_entries(directory, uid, max_entry_bytes))
    return directory


def enable_compilation_cache(
    path: str | os.PathLike | None = None,
    *,
    max_entry_bytes: int = DEFAULT_MAX_ENTRY_BYTES,
    min_compile_time_secs: float = 0.0,
) -> Path:
    """Turn on JAX's persistent compilation cache in a checked directory; returns it.

    **Arguments:**

    - ``path``: the cache directory; default `default_cache_directory`.
    - ``max_entry_bytes``: refuse a directory holding a larger entry.
    - ``min_compile_time_secs``: programs that compile faster than this are not stored (JAX's
      own default is 1 s, which would skip most of jaxlag's programs).

    This sets ``jax_compilation_cache_dir`` and ``jax_persistent_cache_min_compile_time_secs``
    for the whole process, which is why it is the user's call and never done on import. Call it
    before the first computation. Raises `UnsafeCacheDirectory` (and changes nothing)
    when the directory is not safe to load programs from. Entries written since the last call
    that fail to decompress (truncated by a killed writer) are removed, with one warning, and
    compiled again; entries a umask left group- or world-writable in the private directory are
    set to 0600 (see the module docstring for why they were safe all along).

    JAX does not store programs that contain host callbacks; a ``jl.simulate`` whose save times
    are traced (inside your own ``jit``) carries diffrax's checks of them as callbacks.
    """
    directory = checked_cache_directory(path, max_entry_bytes=max_entry_bytes)
    jax.config.update("jax_compilation_cache_dir", str(directory))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_time_secs))
    return directory
