"""The opt-in compilation cache: a directory checked as ssh checks its keys, then JAX's own cache.

Every unsafe case of the cache directory is refused with a message that names it; nothing in
these tests turns JAX's cache on in the test process (the end-to-end case runs in subprocesses).
"""

from __future__ import annotations

import os
import stat
import subprocess
import sys
import threading
import time
import warnings
import zlib
from pathlib import Path

import jax
import pytest

import jaxlag as jl
import jaxlag._cache as cache
from jaxlag._cache import checked_cache_directory


def _mode(path) -> int:
    return stat.S_IMODE(os.lstat(path).st_mode)


def test_import_changes_no_jax_setting():
    script = (
        "import jax\n"
        "names = [n for n in dir(jax.config) if n.startswith('jax_')]\n"
        "def snap():\n"
        "    out = {}\n"
        "    for n in names:\n"
        "        try: out[n] = repr(getattr(jax.config, n))\n"
        "        except Exception: pass\n"
        "    return out\n"
        "before = snap(); import jaxlag; after = snap()\n"
        "print(sorted(k for k in before if before[k] != after.get(k)))\n"
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "[]"


def test_created_private_whatever_the_umask(tmp_path):
    old = os.umask(0)
    try:
        directory = checked_cache_directory(tmp_path / "a" / "b" / "jax")
    finally:
        os.umask(old)
    assert directory == tmp_path / "a" / "b" / "jax"
    for path in (tmp_path / "a", tmp_path / "a" / "b", directory):
        assert _mode(path) == 0o700


def test_default_directory_follows_xdg_and_ignores_relative_paths(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert jl.default_cache_directory() == tmp_path / "xdg" / "jaxlag" / "jax"
    monkeypatch.setenv("XDG_CACHE_HOME", "relative/cache")  # the XDG spec: ignore it
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert jl.default_cache_directory() == tmp_path / "home" / ".cache" / "jaxlag" / "jax"
    monkeypatch.setenv("HOME", "")
    with pytest.raises(jl.UnsafeCacheDirectory, match="absolute path"):
        jl.default_cache_directory()  # never /.cache
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", "home")
    with pytest.raises(jl.UnsafeCacheDirectory, match="absolute path"):
        jl.default_cache_directory()


def test_symlinked_directory_is_refused(tmp_path):
    elsewhere = tmp_path / "someone_elses"
    elsewhere.mkdir(mode=0o700)
    (tmp_path / "cache").symlink_to(elsewhere)
    with pytest.raises(jl.UnsafeCacheDirectory, match="symbolic link"):
        checked_cache_directory(tmp_path / "cache")
    (tmp_path / "parent").symlink_to(elsewhere)
    with pytest.raises(jl.UnsafeCacheDirectory, match="symbolic link"):
        checked_cache_directory(tmp_path / "parent" / "jax")


@pytest.mark.parametrize("mode", [0o770, 0o707, 0o777])
def test_group_or_world_writable_directory_is_refused(tmp_path, mode):
    directory = tmp_path / "jax"
    directory.mkdir()
    os.chmod(directory, mode)
    with pytest.raises(jl.UnsafeCacheDirectory, match="writable by group or others"):
        checked_cache_directory(directory)
    os.chmod(directory, 0o700)
    os.chmod(tmp_path, 0o777)  # an ancestor
    try:
        with pytest.raises(jl.UnsafeCacheDirectory, match="writable by group or others"):
            checked_cache_directory(directory)
    finally:
        os.chmod(tmp_path, 0o700)


def test_directory_created_by_another_user_is_refused(tmp_path, monkeypatch):
    directory = tmp_path / "shared_xdg" / "jaxlag" / "jax"
    directory.mkdir(parents=True)
    for path in (tmp_path / "shared_xdg", tmp_path / "shared_xdg" / "jaxlag", directory):
        os.chmod(path, 0o700)
    # As seen by another user: the directories belong to someone else.
    monkeypatch.setattr(os, "getuid", lambda: os.geteuid() + 4321)
    with pytest.raises(jl.UnsafeCacheDirectory, match="owned by uid"):
        checked_cache_directory(directory)


def test_planted_entries_are_refused(tmp_path, monkeypatch):
    directory = checked_cache_directory(tmp_path / "jax")
    planted = directory / "jit_solve-0123456789abcdef-cache"
    planted.write_bytes(b"not a program")
    os.chmod(planted, 0o600)
    checked_cache_directory(directory)  # the user's own private file: fine
    monkeypatch.setattr(os, "getuid", lambda: os.geteuid() + 4321)
    monkeypatch.setattr(os, "lstat", _lstat_owned_by(os.geteuid() + 4321, tmp_path))
    with pytest.raises(jl.UnsafeCacheDirectory, match="entry is owned by uid"):
        checked_cache_directory(directory)


@pytest.mark.parametrize("mode", [0o664, 0o666])
def test_entry_modes_matter_only_where_others_can_enter(tmp_path, mode):
    """In the private (0700) directory a group/world-writable entry is unreachable by others: it
    is accepted and set to 0600. In a directory others can enter, it is refused, with the fix."""
    directory = checked_cache_directory(tmp_path / "jax")
    entry = directory / "jit_solve-0123456789abcdef-cache"
    entry.write_bytes(b"not a program")
    os.chmod(entry, mode)
    checked_cache_directory(directory)
    assert _mode(entry) == 0o600
    os.chmod(directory, 0o755)  # the user opened it up: others can reach the entries
    checked_cache_directory(directory)  # entries already private: fine
    os.chmod(entry, mode)
    with pytest.raises(
        jl.UnsafeCacheDirectory, match=r"writable by group or others, who can enter.*chmod 700"
    ):
        checked_cache_directory(directory)
    assert _mode(entry) == mode  # refused: nothing changed


def test_hard_linked_entry_is_refused(tmp_path):
    directory = checked_cache_directory(tmp_path / "jax")
    entry = directory / "jit_solve-0123456789abcdef-cache"
    entry.write_bytes(b"not a program")
    os.link(entry, tmp_path / "outside")  # writable through a path outside the directory
    with pytest.raises(jl.UnsafeCacheDirectory, match="2 hard links"):
        checked_cache_directory(directory)


def _entry(directory, name, payload: bytes) -> Path:
    """A cache entry as JAX's file cache writes it: ``<key>-cache``, zlib-compressed."""
    path = directory / f"{name}-cache"
    path.write_bytes(zlib.compress(payload))
    return path


def test_truncated_and_empty_entries_are_removed_with_one_warning(tmp_path):
    directory = checked_cache_directory(tmp_path / "jax")
    good = _entry(directory, "jit_good-0", bytes(range(256)) * 64)
    truncated = _entry(directory, "jit_truncated-1", bytes(range(256)) * 64)
    truncated.write_bytes(truncated.read_bytes()[:100])  # a writer killed mid-write
    empty = directory / "jit_empty-2-cache"
    empty.write_bytes(b"")  # killed before its first write
    unknown = directory / "jit_unknown-3-cache"
    unknown.write_bytes(b"not a format jaxlag knows: left to JAX")
    with pytest.warns(RuntimeWarning, match=r"Removed 2 damaged compilation cache entries") as record:
        checked_cache_directory(directory)
    assert len(record) == 1 and "jit_truncated-1-cache" in str(record[0].message)
    assert not truncated.exists() and not empty.exists()
    assert good.exists() and unknown.exists()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        checked_cache_directory(directory)  # nothing left to repair: silent


def test_only_entries_written_since_the_last_call_are_read(tmp_path, monkeypatch):
    """The cost of a call is a stat per entry, not a read: ``.jaxlag-verified`` records when the
    entries were last read, and only those modified since (within the file system's timestamp
    resolution) are read again."""
    directory = checked_cache_directory(tmp_path / "jax")
    old = _entry(directory, "jit_old-0", b"x" * 1000)
    day_ago = time.time() - 86400
    os.utime(old, (day_ago, day_ago))
    read = []
    damaged = cache._damaged
    monkeypatch.setattr(cache, "_damaged", lambda path: read.append(path.name) or damaged(path))
    checked_cache_directory(directory)
    assert read == []  # older than the last call
    new = _entry(directory, "jit_new-1", b"y" * 1000)
    checked_cache_directory(directory)
    assert read == [new.name]
    os.unlink(directory / ".jaxlag-verified")  # no record: every entry is read once
    read.clear()
    checked_cache_directory(directory)
    assert sorted(read) == sorted([old.name, new.name])


def _lstat_owned_by(uid, root):
    """``os.lstat`` that reports the test user's directories as owned by ``uid`` (the entries,
    read through ``os.scandir``, keep their real owner: someone else's, as seen by ``uid``).
    Run as root, only the directories under ``root`` (system directories stay root's)."""
    real, me = os.lstat, os.geteuid()

    def owned(info):
        # A real os.stat_result (jaxlag's annotations say so, and the suite checks them), with
        # st_uid replaced; the fields outside the tuple (st_mtime_ns, ...) are passed by name.
        values = list(info)
        values[4] = uid  # st_uid
        return os.stat_result(values, {k: getattr(info, k) for k in dir(info) if k.startswith("st_")})

    def lstat(path, *a, **k):
        info = real(path, *a, **k)
        mine = info.st_uid == me and (me != 0 or str(path).startswith(str(root)))
        return owned(info) if mine else info

    return lstat


def test_fifo_and_device_links_are_refused_without_reading(tmp_path):
    directory = checked_cache_directory(tmp_path / "jax")
    fifo = directory / "jit_solve-fifo-cache"
    os.mkfifo(fifo, 0o600)
    result = {}
    worker = threading.Thread(target=lambda: result.update(error=_refusal(directory)))
    worker.start()
    worker.join(timeout=30)
    assert not worker.is_alive(), "the check opened the FIFO"
    assert "not a regular file" in result["error"]
    os.unlink(fifo)
    (directory / "jit_solve-zero-cache").symlink_to("/dev/zero")
    assert "symbolic link" in _refusal(directory)


def _refusal(directory) -> str:
    try:
        checked_cache_directory(directory)
    except jl.UnsafeCacheDirectory as error:
        return str(error)
    return ""


def test_oversized_entry_is_refused(tmp_path):
    directory = checked_cache_directory(tmp_path / "jax")
    big = directory / "jit_big-cache"
    with open(big, "wb") as f:
        f.truncate(2048)
    os.chmod(big, 0o600)
    with pytest.raises(jl.UnsafeCacheDirectory, match="2048 bytes"):
        checked_cache_directory(directory, max_entry_bytes=1024)


def test_stale_temporaries_of_a_killed_writer_are_removed(tmp_path):
    directory = checked_cache_directory(tmp_path / "jax")
    stale, fresh = directory / "jit_x-cache.tmp", directory / "jit_y-cache.tmp"
    for path in (stale, fresh):
        path.write_bytes(b"partial")
        os.chmod(path, 0o600)
    old = time.time() - 7200
    os.utime(stale, (old, old))
    checked_cache_directory(directory)
    assert not stale.exists()
    assert fresh.exists()  # may belong to a writer still running


_SCRIPT = """
import jax, jax.numpy as jnp
hits = []
jax.monitoring.register_event_listener(
    lambda e, **k: hits.append(e) if e == '/jax/compilation_cache/cache_hits' else None)
import jaxlag as jl
jax.config.update('jax_enable_x64', True)
directory = jl.enable_compilation_cache()
s = jl.System(lambda q, qd, args: 0.5 * qd[0] ** 2 - 0.5 * args['k'] * q[0] ** 2)
q = jl.simulate(s, jnp.array([1.0]), jnp.zeros(1), jnp.linspace(0, 1, 3), args={'k': 1.0}).q
print(directory, len(hits), float(q[-1, 0]))
"""


def test_enable_compilation_cache_end_to_end(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    env["XDG_CACHE_HOME"] = str(tmp_path)

    def run():
        out = subprocess.run(
            [sys.executable, "-c", _SCRIPT], env=env, capture_output=True, text=True, timeout=600
        )
        assert out.returncode == 0, out.stderr[-2000:]
        directory, hits, value = out.stdout.split()
        return directory, int(hits), float(value)

    directory, first_hits, value = run()
    assert directory == str(tmp_path / "jaxlag" / "jax")
    assert _mode(directory) == 0o700
    assert any(entry.name.endswith("-cache") for entry in os.scandir(directory))  # programs were stored
    _, second_hits, second_value = run()
    assert second_hits > first_hits  # the second process read what the first wrote
    assert second_value == value
    os.chmod(directory, 0o770)
    env_unsafe = subprocess.run(
        [sys.executable, "-c", _SCRIPT], env=env, capture_output=True, text=True, timeout=600
    )
    assert env_unsafe.returncode != 0
    assert "UnsafeCacheDirectory" in env_unsafe.stderr
    assert "writable by group or others" in env_unsafe.stderr


def test_enable_sets_only_the_cache_settings(tmp_path, monkeypatch):
    """The call's whole effect on JAX: the two cache settings (restored after this test)."""
    updates = []
    monkeypatch.setattr(jax.config, "update", lambda name, value: updates.append((name, value)))
    directory = jl.enable_compilation_cache(tmp_path / "jax", min_compile_time_secs=0.5)
    assert updates == [
        ("jax_compilation_cache_dir", str(directory)),
        ("jax_persistent_cache_min_compile_time_secs", 0.5),
    ]


# A small program (stored whatever its compile time), the cache hits counted, warnings printed.
_SMALL = """
import os, sys, warnings
os.umask(int(sys.argv[1], 8))
warnings.simplefilter("always")
import jax, jax.numpy as jnp
hits = []
jax.monitoring.register_event_listener(
    lambda e, **k: hits.append(e) if e == '/jax/compilation_cache/cache_hits' else None)
import jaxlag as jl
jl.enable_compilation_cache()
print(float(jax.jit(lambda x: jnp.sin(x) * 2.0)(1.0)), len(hits))
"""


def _run_small(tmp_path, umask: int):
    """``(value, cache hits, stderr)`` of one process running `_SMALL` with the cache under
    ``tmp_path`` and the given umask."""
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    env["XDG_CACHE_HOME"] = str(tmp_path)
    out = subprocess.run(
        [sys.executable, "-c", _SMALL, f"{umask:o}"], env=env, capture_output=True, text=True, timeout=600
    )
    assert out.returncode == 0, out.stderr[-2000:]
    value, hits = out.stdout.split()
    return float(value), int(hits), out.stderr


def _programs(directory):
    return sorted(p for p in Path(directory).iterdir() if p.name.endswith("-cache"))


@pytest.mark.parametrize("umask", [0o000, 0o002])
def test_the_users_own_cache_is_accepted_whatever_the_umask(tmp_path, umask):
    """JAX writes its entries with the mode the umask leaves (0666, 0664): in the private
    directory nobody else can reach them, so the second process accepts and reuses them, and
    they are set to 0600 (the user's alone) from then on."""
    value, hits, _ = _run_small(tmp_path, umask)
    directory = tmp_path / "jaxlag" / "jax"
    assert hits == 0 and _mode(directory) == 0o700
    written = _programs(directory)
    assert written and all(_mode(p) == 0o666 & ~umask for p in written)  # as JAX writes them
    second_value, second_hits, stderr = _run_small(tmp_path, umask)
    assert second_hits >= 1 and second_value == value, stderr[-2000:]
    assert all(_mode(p) == 0o600 for p in written)


def test_an_entry_truncated_by_a_killed_writer_is_rewritten(tmp_path):
    """Truncated after the first run: the second run removes it (one warning, JAX's own never
    appears) and stores the program again; the third run reads it and says nothing."""
    value, _, _ = _run_small(tmp_path, 0o022)
    (entry,) = _programs(tmp_path / "jaxlag" / "jax")
    whole = entry.read_bytes()
    with open(entry, "r+b") as file:
        file.truncate(len(whole) // 2)
    second_value, second_hits, second_err = _run_small(tmp_path, 0o022)
    assert second_hits == 0 and second_value == value
    assert second_err.count("Warning") == 1 and "Removed 1 damaged compilation cache entries" in second_err
    assert "Error reading persistent compilation cache" not in second_err
    assert not cache._damaged(entry)  # stored again, whole
    third_value, third_hits, third_err = _run_small(tmp_path, 0o022)
    assert third_hits >= 1 and third_value == value
    assert "Warning" not in third_err, third_err[-2000:]
