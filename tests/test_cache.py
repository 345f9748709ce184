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

import jax
import pytest

import jaxlag as jl
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
    os.chmod(planted, 0o666)
    with pytest.raises(jl.UnsafeCacheDirectory, match="writable by group or others"):
        checked_cache_directory(directory)
    os.chmod(planted, 0o600)
    checked_cache_directory(directory)  # the user's own private file: fine
    monkeypatch.setattr(os, "getuid", lambda: os.geteuid() + 4321)
    monkeypatch.setattr(os, "lstat", _lstat_owned_by(os.geteuid() + 4321, tmp_path))
    with pytest.raises(jl.UnsafeCacheDirectory, match="entry is owned by uid"):
        checked_cache_directory(directory)


def _lstat_owned_by(uid, root):
    """``os.lstat`` that reports the test user's directories as owned by ``uid`` (the entries,
    read through ``os.scandir``, keep their real owner: someone else's, as seen by ``uid``).
    Run as root, only the directories under ``root`` (system directories stay root's)."""
    real, me = os.lstat, os.geteuid()

    class Info:
        def __init__(self, info):
            self._info = info

        def __getattr__(self, name):
            return uid if name == "st_uid" else getattr(self._info, name)

    def lstat(path, *a, **k):
        info = real(path, *a, **k)
        mine = info.st_uid == me and (me != 0 or str(path).startswith(str(root)))
        return Info(info) if mine else info

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
    assert any(os.scandir(directory))  # programs were stored
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
