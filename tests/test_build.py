"""The build itself: the native module imports, memory crosses the binding without a copy,
and the CLI's fixed behaviour holds."""
import subprocess
import sys

import numpy as np
import pytest

import exolan


def test_native_module_imports_with_matching_version():
    assert exolan._native is not None
    assert exolan.native_version == exolan.__version__


def test_numpy_round_trip_is_zero_copy():
    a = np.arange(6, dtype=np.float64)
    addr = exolan._native.scale_in_place(a, 2.0)
    assert addr == a.ctypes.data  # Rust worked on numpy's own buffer
    np.testing.assert_array_equal(a, 2.0 * np.arange(6))
    assert exolan._native.sum(a) == pytest.approx(30.0)


def test_native_rejects_wrong_dtype():
    with pytest.raises(TypeError):
        exolan._native.sum(np.arange(3, dtype=np.int64))


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "exolan.cli", *args], capture_output=True, text=True)


def test_cli_version_and_doctor():
    r = _cli("--version")
    assert r.returncode == 0 and exolan.__version__ in r.stdout
    r = _cli("doctor")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "native build matches python package: yes" in r.stdout
    assert "torch" in r.stdout


def test_crate_builds_without_python():
    # the pure-Rust core must not need pyo3: build it with the python feature off
    r = subprocess.run(["cargo", "check", "--no-default-features", "--lib", "--quiet"],
                       capture_output=True, text=True, cwd=exolan.__file__.rsplit("/python/", 1)[0])
    assert r.returncode == 0, r.stderr
