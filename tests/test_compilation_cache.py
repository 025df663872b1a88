"""Compiled programs (`lgnn.runtime`): the persistent compilation cache (where it lives,
how it is turned off, and that an unwritable place means no cache rather than an
error), and their release once a process holds too many memory mappings."""

import os

import jax

from lgnn.runtime import COMPILATION_CACHE_ENV, compilation_cache_dir, enable_compilation_cache


def test_cache_directory_from_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv(COMPILATION_CACHE_ENV, str(tmp_path / "mine"))
    assert compilation_cache_dir() == str(tmp_path / "mine")
    for off in ("off", "0", "", "none"):
        monkeypatch.setenv(COMPILATION_CACHE_ENV, off)
        assert compilation_cache_dir() is None and enable_compilation_cache() is None
    monkeypatch.delenv(COMPILATION_CACHE_ENV)
    monkeypatch.delenv("LGNN_CACHE", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert compilation_cache_dir() == os.path.join(str(tmp_path), "lgnn", "jax")


def test_unwritable_cache_directory_means_no_cache(monkeypatch):
    monkeypatch.setenv(COMPILATION_CACHE_ENV, "/proc/lgnn-cannot-be-here/jax")
    before = jax.config.jax_compilation_cache_dir
    assert enable_compilation_cache() is None
    assert jax.config.jax_compilation_cache_dir == before


def test_tests_run_with_a_cache_of_their_run_never_the_users():
    # conftest.py gives the tests, and the processes they start, a cache in a temporary
    # folder of the test run's, one for all its xdist workers (the controller made it);
    # the user's (`~/.cache/lgnn/jax`) is never read or written.
    import tempfile

    from lgnn.files import user_cache_dir

    directory = os.environ[COMPILATION_CACHE_ENV]
    assert jax.config.jax_compilation_cache_dir == directory == os.environ["LGNN_TEST_JAX_CACHE"]
    assert os.path.isdir(directory)
    assert directory.startswith(tempfile.gettempdir()) and not directory.startswith(str(user_cache_dir()))


def test_compiled_programs_are_released_only_above_the_mapping_limit():
    """Each compiled program holds memory mappings until released; a process above
    `above` mappings drops them all (`release_compiled_programs`), one below keeps them."""
    import jax.numpy as jnp

    from lgnn.runtime import memory_mappings, release_compiled_programs

    programs = [jax.jit(lambda x, k=k: jnp.sin(x) * k + jnp.cos(x) ** 2) for k in range(60)]
    for program in programs:
        program(jnp.ones(3)).block_until_ready()
    before = memory_mappings()
    assert not release_compiled_programs(above=before + 10_000)
    assert all(program._cache_size() == 1 for program in programs)
    assert release_compiled_programs(above=0)
    assert all(program._cache_size() == 0 for program in programs)
    assert memory_mappings() < before - len(programs)  # at least one mapping each returned


def test_tests_compile_with_most_optimisations_off():
    # conftest.py sets it before JAX loads (JAX reads it once, as its compiler loads).
    assert jax.config.values["jax_disable_most_optimizations"]
