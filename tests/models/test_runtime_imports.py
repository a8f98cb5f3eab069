"""The daemon's side stays light: importing compd.daemon.app and building and stepping every model kind
from its model file loads none of the fit/plot libraries (scipy, matplotlib, tqdm, sklearn, statsmodels)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import yaml

from rig.bench_models import BUILDERS

HEAVY = ("scipy", "matplotlib", "tqdm", "sklearn", "statsmodels")
ROOT = Path(__file__).resolve().parents[2]

CHILD = r"""
import json, sys
from pathlib import Path

import numpy as np

import compd.daemon.app
from compd.config import load_model_file, resolve_model

heavy = {HEAVY!r}
seen = {{"import compd.daemon.app": sorted({{m for m in sys.modules if m.split(".")[0] in heavy}})}}
for file in sys.argv[1:]:
    p = Path(file)
    doc, data = load_model_file(p)
    spec = resolve_model({{"kind": data["kind"], "file": str(p)}}, doc, (), p.parent)
    model = compd.cycle.pipeline.build_model(spec)
    x = np.linspace(20.0, 21.0, len(model.inputs))
    out = np.zeros(len(model.outputs))
    model.start(x, 0.0)
    for k in range(1, 50):
        model.evaluate(x + 0.01 * k, 60.0 * k, out)
    assert np.all(np.isfinite(out)), (data["kind"], out)
    model.linear_terms()
    model.get_status()
    model.predict(np.tile(x, (5, 1)), np.arange(5) * 60.0)
    seen[data["kind"]] = sorted({{m for m in sys.modules if m.split(".")[0] in heavy}})
print(json.dumps(seen))
"""


def test_daemon_imports_no_fit_or_plot_library(tmp_path: Path) -> None:
    files = []
    for kind, build in BUILDERS.items():
        f = tmp_path / f"{kind}.yaml"
        f.write_text(yaml.safe_dump(json.loads(json.dumps(build().to_dict())), sort_keys=False))
        files.append(str(f))
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    p = subprocess.run(
        [sys.executable, "-c", CHILD.format(HEAVY=HEAVY), *files],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
        timeout=120,
    )
    assert p.returncode == 0, p.stderr
    seen = json.loads(p.stdout)
    assert set(seen) == {"import compd.daemon.app", *BUILDERS}
    assert seen == {k: [] for k in seen}, seen
