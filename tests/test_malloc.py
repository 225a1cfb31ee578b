"""``jaxfit._malloc``: the freed host arrays of one fit are not mapped again by the next."""

import json
import os
import subprocess
import sys

import pytest

from jaxfit import _malloc

# A fit's pattern of host memory: several ~1 MB temporaries alive at once, then all freed.
CHURN = """
import json, resource, numpy as np
import jaxfit, jaxfit._malloc as m
def churn():
    arrays = [np.ones(1 << 17) for _ in range(8)]
    return sum(float(a[0]) for a in arrays)
churn()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(20):
    churn()
faults = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 20
print(json.dumps([m.applied, faults]))
"""


def churn(setting: str | None) -> tuple[bool, float]:
    """(whether jaxfit set malloc's parameters, page faults per round of CHURN) in a
    fresh interpreter with JAXFIT_MALLOC=setting (None: unset)."""
    env = {k: v for k, v in os.environ.items() if k != _malloc.ENVIRONMENT}
    if setting is not None:
        env[_malloc.ENVIRONMENT] = setting
    proc = subprocess.run([sys.executable, "-c", CHURN], env=env, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return tuple(json.loads(proc.stdout.strip().splitlines()[-1]))


@pytest.mark.skipif(not _malloc.applied, reason="malloc's parameters are glibc's only "
                    "(or JAXFIT_MALLOC=0 is set for the tests)")
def test_freed_arrays_stay_mapped_and_the_setting_turns_it_off():
    applied, faults = churn(None)
    left, left_faults = churn("0")
    assert applied and not left
    # 8 MB freed and made again per round: 2,048 pages if they go back to the system.
    assert left_faults > 1000
    assert faults < 0.05 * left_faults


def test_an_unknown_setting_warns_and_off_values_are_the_caches(monkeypatch):
    monkeypatch.setattr(_malloc, "applied", None)
    monkeypatch.setenv(_malloc.ENVIRONMENT, "maybe")
    monkeypatch.setattr(_malloc.sys, "platform", "darwin")  # (nothing set in this process)
    with pytest.warns(RuntimeWarning, match="JAXFIT_MALLOC='maybe' is not understood"):
        assert _malloc.keep_freed_memory() is False
    for off in ("0", "off", " False "):
        monkeypatch.setattr(_malloc, "applied", None)
        monkeypatch.setenv(_malloc.ENVIRONMENT, off)
        monkeypatch.setattr(_malloc.sys, "platform", "linux")
        assert _malloc.keep_freed_memory() is False


def test_keep_freed_memory_is_set_once():
    first = _malloc.applied
    assert _malloc.keep_freed_memory() is first
