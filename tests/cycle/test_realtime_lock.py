"""loop.realtime.lock_memory: mlockall locks pages as they are touched, not every page mapped."""

from __future__ import annotations

import json
import subprocess
import sys

SCRIPT = """
import json, numpy
from compd.cycle.realtime import _mlockall
def rss():
    for line in open('/proc/self/status'):
        if line.startswith('VmRSS'):
            return int(line.split()[1])
before = rss()
err, onfault = _mlockall()
print(json.dumps({'err': err, 'onfault': onfault, 'before_kb': before, 'after_kb': rss()}))
"""


def test_locking_memory_does_not_make_every_mapped_page_resident():
    # in a process of its own: the lock would outlive the test in pytest's
    r = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    if out["err"] != 0:  # not allowed here (RLIMIT_MEMLOCK): compd reports it and runs unlocked
        assert out["err"] > 0 and not out["onfault"]
        return
    # numpy's OpenBLAS alone maps tens of MB of text; locked as touched, the size barely moves
    assert out["onfault"], out
    assert out["after_kb"] - out["before_kb"] < 10_000, out
