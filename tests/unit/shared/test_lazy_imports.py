"""The pieces a service defers still work when asked for: open3d's plotly drawing through shared.o3d's
stand-in, the mapper core's names through shared.lazy. That the service processes start without them is
tests/unit/test_import_cost.py's check."""

import pytest

import services.mapper.core as mapper_core
from shared.o3d import o3d


def test_open3ds_plotly_drawing_loads_on_its_first_call():
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]))
    assert type(o3d.visualization.get_plotly_fig([cloud])).__name__ == "Figure"


def test_every_name_the_mapper_core_exports_resolves():
    for name in mapper_core.__all__:
        value = getattr(mapper_core, name)
        assert getattr(value, "__name__", name) == name or not callable(value), name
    assert set(mapper_core.__all__) <= set(dir(mapper_core))
    assert "execute_tours" in vars(mapper_core)  # resolved once, then a plain attribute


def test_a_name_the_core_does_not_export_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no_such_name"):
        mapper_core.no_such_name  # noqa: B018
