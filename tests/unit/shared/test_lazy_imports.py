"""What a service process imports at start: robot-io's open3d without plotly/dash (shared.o3d), the mapper
without its exploration (shared.lazy); the deferred pieces still work when asked for."""

import json
import os
import subprocess
import sys
from pathlib import Path

import services.mapper.core as mapper_core

ROOT = Path(__file__).resolve().parents[3]

# One fresh interpreter (a worker has loaded everything already): what each service module brings in, then
# open3d's plotly drawing through the stand-in, which must load the real module on its first call.
PROBE = """
import json, sys
out = {}
import services.robot_io.service
out["robot_io"] = [m for m in ("open3d", "dash", "plotly") if m in sys.modules]
import services.mapper.service
out["mapper"] = [m for m in ("networkx", "scipy.ndimage", "services.mapper.core.exploration_job") if m in sys.modules]
from shared.o3d import o3d
cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]))
out["figure"] = type(o3d.visualization.get_plotly_fig([cloud])).__name__
out["after_figure"] = [m for m in ("dash", "plotly") if m in sys.modules]
print(json.dumps(out))
"""


def test_service_modules_leave_what_they_do_not_serve_for_later():
    run = subprocess.run([sys.executable, "-c", PROBE], cwd=ROOT, capture_output=True, text=True, timeout=120,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert run.returncode == 0, run.stderr[-3000:]
    out = json.loads(run.stdout.splitlines()[-1])
    assert out["robot_io"] == ["open3d"]  # the ray caster, not its plotly/dash drawing
    assert out["mapper"] == []  # prediction only; exploration loads with the first job
    assert out["figure"] == "Figure" and out["after_figure"] == ["dash", "plotly"]


def test_every_name_the_mapper_core_exports_resolves():
    for name in mapper_core.__all__:
        value = getattr(mapper_core, name)
        assert getattr(value, "__name__", name) == name or not callable(value), name
    assert set(mapper_core.__all__) <= set(dir(mapper_core))
    assert "execute_tours" in vars(mapper_core)  # resolved once, then a plain attribute


def test_a_name_the_core_does_not_export_is_an_attribute_error():
    try:
        mapper_core.no_such_name  # noqa: B018
    except AttributeError as exc:
        assert "no_such_name" in str(exc)
    else:
        raise AssertionError("an unknown name resolved")
