"""policy.h compiles for any finite weights (exact zeros, integers, subnormals, ±1e38) and
computes what numpy computes; non-finite weights are refused; the README and policy.json name
the same C function."""

from __future__ import annotations

import ctypes
import os
import re
import shutil
import subprocess

import numpy as np
import pytest

from ttd3_jax.interop import policy as pe

README = os.path.join(os.path.dirname(__file__), "..", "README.md")


@pytest.mark.parametrize(
    "v, want",
    [(0.0, "0.0f"), (-0.0, "-0.0f"), (1.0, "1.0f"), (-3.0, "-3.0f"), (1e38, "9.99999968e+37f"),
     (2.0**-149, "1.40129846e-45f"), (0.5, "0.5f"), (16777216.0, "16777216.0f")],
)  # fmt: skip
def test_every_weight_is_a_c_float_literal_that_reads_back_exactly(v, want):
    assert pe.c_float(v) == want
    assert np.float32(float(want[:-1])) == np.float32(v)


def test_literals_of_random_float32_read_back_exactly():
    x = np.random.default_rng(0).standard_normal(2000).astype(np.float32) * np.float32(10.0) ** np.arange(
        -37, 37, 0.037, dtype=np.float32
    )
    lits = [pe.c_float(v) for v in x]
    assert all(re.fullmatch(r"-?\d+(\.\d*)?(e[+-]\d+)?f|-?\d+e[+-]\d+f", s) and ("." in s or "e" in s)
               for s in lits)  # fmt: skip
    np.testing.assert_array_equal(np.array([float(s[:-1]) for s in lits], np.float32), x)


def awkward_policy() -> pe.Policy:
    """Weights with exact zeros, integers, subnormals and ±1e38 (biases of the tanh layer)."""
    rng = np.random.default_rng(3)
    w0 = np.round(rng.normal(size=(17, 8)) * 2).astype(np.float32)  # integers, many exact zeros
    w0[0, :3] = [2.0**-149, -(2.0**-140), 0.0]
    b0 = np.zeros(8, np.float32)
    w1 = rng.normal(size=(8, 4)).astype(np.float32)
    w1[0, 0] = 1e38
    b1 = np.array([1e38, -1e38, 0.0, 3.0], np.float32)
    return pe.Policy([(w0, b0), (w1, b1)], np.zeros(17, np.float32), np.ones(17, np.float32))


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")
def test_a_header_of_awkward_weights_compiles_and_matches_numpy(tmp_path):
    p = awkward_policy()
    (tmp_path / "policy.h").write_text(pe.c_header(p))
    src = tmp_path / "shim.c"
    src.write_text(
        '#include "policy.h"\nvoid shim(const float *o, float *a) { ttd3_policy_forward(o, a); }\n'
    )
    lib = tmp_path / "libpolicy.so"
    cmd = ["cc", "-std=c99", "-O0", "-Wall", "-Wextra", "-Werror", "-pedantic", "-shared", "-fPIC"]
    subprocess.run([*cmd, "-I", str(tmp_path), str(src), "-o", str(lib), "-lm"], check=True)
    shim = ctypes.CDLL(str(lib)).shim
    obs = np.random.default_rng(0).normal(0.0, 0.5, (64, 17)).astype(np.float32)
    got = np.zeros((len(obs), 4), np.float32)
    for o, a in zip(obs, got, strict=True):
        shim(o.ctypes.data_as(ctypes.c_void_p), a.ctypes.data_as(ctypes.c_void_p))
    with np.errstate(over="ignore"):  # 1e38 x a weight: inf, then tanh(inf) = 1, in C too
        want = pe.forward(p, obs)
    assert np.all(np.isfinite(got)) and got[:, 0].min() == 1.0 and got[:, 1].max() == -1.0
    np.testing.assert_allclose(got, want, atol=1e-5, rtol=0)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_weights_are_refused_and_nothing_is_written(tmp_path, bad):
    p = awkward_policy()
    p.layers[1][0][2, 1] = bad
    meta = {"source": {"run": "r", "seed": 0, "epoch": 1}}
    with pytest.raises(ValueError, match=r"ttd3_w1 holds non-finite values .*earlier --epoch or --best"):
        pe.write(str(tmp_path / "out"), p, meta, onnx=False)
    assert not (tmp_path / "out").exists()


def test_the_readme_and_policy_json_name_the_header_function():
    header = pe.c_header(awkward_policy())
    assert "static void ttd3_policy_forward(const float *obs, float *action)" in header
    readme = open(README).read()
    assert "ttd3_policy_forward(const float *obs, float *action)" in readme
    assert "#define policy_forward ttd3_policy_forward" in header and "TTD3_NO_SHORT_NAMES" in readme
