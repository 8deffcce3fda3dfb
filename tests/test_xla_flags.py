"""nhjax's one process-wide XLA setting (nhjax/_xla_flags.py): small time-stepping
loops compiled as one function. Checked in fresh processes, since XLA reads its flags
once per process."""

import json
import os
import subprocess
import sys

import pytest

from nhjax import _xla_flags as X

KEY = X.KEY


def test_merged_flags_keeps_what_the_user_set():
    assert X.merged_flags("", 4096) == f"--xla_backend_extra_options={KEY}=4096"
    assert X.merged_flags("--xla_force_host_platform_device_count=2", 7) == (
        f"--xla_force_host_platform_device_count=2 --xla_backend_extra_options={KEY}=7")
    # other backend options already given: one merged entry, theirs first
    merged = X.merged_flags("--a=1 --xla_backend_extra_options=xla_cpu_fold_all_constants=1 --b=2", 9)
    assert merged == f"--a=1 --xla_backend_extra_options=xla_cpu_fold_all_constants=1,{KEY}=9 --b=2"
    # the user's own threshold wins
    mine = f"--xla_backend_extra_options={KEY}=123"
    assert X.merged_flags(mine, 65536) == mine


def test_configure_switches():
    env = {"NHJAX_SMALL_LOOP_BYTES": "0", "XLA_FLAGS": "--x=1"}
    assert X.configure(env) == "off" and env["XLA_FLAGS"] == "--x=1"
    env = {"XLA_FLAGS": f"--xla_backend_extra_options={KEY}=5"}
    assert X.configure(env) == "user" and env["XLA_FLAGS"].endswith("=5")
    with pytest.raises(ValueError, match="NHJAX_SMALL_LOOP_BYTES"):
        X.configure({"NHJAX_SMALL_LOOP_BYTES": "lots"})


_PROBE = r"""
import json, re, warnings
warnings.simplefilter("always")
with warnings.catch_warnings(record=True) as caught:
    if EARLY_JAX:
        import jax.numpy as jnp
        jnp.ones(1).block_until_ready()   # the backend starts before nhjax is imported
    import nhjax
import jax, jax.numpy as jnp
from nhjax.scenes import FallingCat
cat = FallingCat()
x0 = jnp.array([0.3, -0.2, 0.1, 0.0, 0.0])
f = jax.jit(lambda x: nhjax.simulate(cat, x, 2.0, saveat=5, diagnostics=False).xs)
text = f.lower(x0).compile().as_text()
# while loops compiled as one function (XLA's own default already takes the tiniest:
# the step-size search, a save-time loop)
hoisted = [l for l in text.splitlines() if "xla_cpu_small_call" in l]
print(json.dumps(dict(hoisted=len(hoisted), xs=f(x0).tolist(),
                      warned=[str(w.message) for w in caught if "imported after" in str(w.message)])))
"""


def _probe(early_jax=False, **env):
    code = _PROBE.replace("EARLY_JAX", str(early_jax))
    full_env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "NHJAX_SMALL_LOOP_BYTES")}
    full_env.update(env)
    out = subprocess.run([sys.executable, "-c", code], env=full_env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.slow  # (a subprocess, 15 s; make test-all)
def test_small_loops_are_compiled_as_one_function_and_give_the_same_numbers():
    on = _probe()
    off = _probe(NHJAX_SMALL_LOOP_BYTES="0")
    late = _probe(early_jax=True)
    # the time-stepping loop is one more only with the setting
    assert on["hoisted"] > off["hoisted"] and late["hoisted"] == off["hoisted"]
    assert not on["warned"] and not off["warned"]
    assert len(late["warned"]) == 1 and "before the first JAX computation" in late["warned"][0]
    import numpy as np

    # the same operations, compiled in one function or kernel by kernel
    np.testing.assert_allclose(on["xs"], off["xs"], rtol=0, atol=1e-13)
    np.testing.assert_allclose(late["xs"], off["xs"], rtol=0, atol=1e-13)
