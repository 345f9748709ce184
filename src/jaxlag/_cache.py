"""Opt-in cross-process compilation cache: JAX's own persistent cache in a checked directory.

Nothing here runs on ``import jaxlag``: JAX's configuration is the user's. A research script that
wants its second run to skip XLA compilation calls `enable_compilation_cache` once, before
its first computation::

    import jaxlag as jl
    jl.enable_compilation_cache()          # $XDG_CACHE_HOME/jaxlag/jax, default ~/.cache/jaxlag/jax

The directory is checked the way ssh checks the files under ``~/.ssh`` before it trusts them,
because whoever can write a cache entry chooses the code the next run executes:

* every directory from the cache root down to the cache directory is owned by the user (or
  root, for the ancestors) and is not group- or world-writable, and none of them is a symlink;
* the cache directory itself is created with mode 0700 (whatever the umask), or, if it
  exists, must be owned by the user and not writable by group or others;
* every entry already in it must be a regular file (no symlinks, FIFOs, devices or
  sub-directories) no larger than ``max_entry_bytes``, owned by the user and not group- or
  world-writable;
* stale temporaries (``*.tmp``/``*.partial`` files older than an hour, left by a killed writer)
  are removed;
* ``HOME`` and ``XDG_CACHE_HOME`` are used only when they are absolute paths (the XDG base
  directory specification says to ignore relative ones); an empty or relative ``HOME`` with no
  usable ``XDG_CACHE_HOME`` is an error, not ``/.cache``.

An unsafe directory is refused with `UnsafeCacheDirectory`, whose message says which
path and why. JAX itself writes and
reads them through its own file cache (a truncated entry, from a writer killed mid-write, is
reported by JAX with a warning and the program compiled again); jaxlag stores no Python objects
and loads no executables of its own.
"""

import os
import stat
import time
from pathlib import Path

import jax

__all__ = ["UnsafeCacheDirectory", "default_cache_directory", "enable_compilation_cache"]

#: Entries larger than this are refused (JAX's largest jaxlag program is a few MB).
DEFAULT_MAX_ENTRY_BYTES = 256 * 2**20
_STALE_SECONDS = 3600.0
_TEMPORARY_SUFFIXES = (".tmp", ".partial")


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


def _check_entries(path: Path, uid: int, max_entry_bytes: int) -> None:
    """Every entry is a regular file of the user's, private to them and of bounded size; stale
    temporaries of a killed writer are removed."""
    now = time.time()
    with os.scandir(path) as entries:
        for entry in entries:
            info = entry.stat(follow_symlinks=False)
            where = path / entry.name
            if not stat.S_ISREG(info.st_mode):
                kind = "a symbolic link" if stat.S_ISLNK(info.st_mode) else "not a regular file"
                raise _refuse(where, f"the cache entry is {kind}")
            if info.st_uid != uid:
                raise _refuse(where, f"the cache entry is owned by uid {info.st_uid}, not by you")
            if info.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
                raise _refuse(where, "the cache entry is writable by group or others")
            if entry.name.endswith(_TEMPORARY_SUFFIXES) and now - info.st_mtime > _STALE_SECONDS:
                os.unlink(where)
                continue
            if info.st_size > max_entry_bytes:
                raise _refuse(
                    where,
                    f"the cache entry has {info.st_size} bytes, more than max_entry_bytes={max_entry_bytes}",
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
    _check_entries(directory, uid, max_entry_bytes)
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
    when the directory is not safe to load programs from.

    JAX does not store programs that contain host callbacks; a ``jl.simulate`` whose save times
    are traced (inside your own ``jit``) carries diffrax's checks of them as callbacks.
    """
    directory = checked_cache_directory(path, max_entry_bytes=max_entry_bytes)
    jax.config.update("jax_compilation_cache_dir", str(directory))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_time_secs))
    return directory
