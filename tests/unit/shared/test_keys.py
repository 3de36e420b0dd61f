import pytest

from shared import keys
from shared.bus.keyexpr import intersects


def test_format_validates_parts():
    assert keys.IO_OBSERVE.format(robot="stretch-1") == "ant/stretch-1/io/observe"
    assert keys.MAP_INFO.format(map="house_0.v2") == "ant/maps/house_0.v2/info"
    for bad in ["*", "**", "a/b", "", "$x", "a b", "x" * 65, "-lead"]:
        with pytest.raises(keys.KeyExprError):
            keys.IO_OBSERVE.format(robot=bad)
    with pytest.raises(keys.KeyExprError, match="missing"):
        keys.MAP_INFO.format()


def test_patterns_use_wildcards_for_missing_parts():
    assert keys.ALIVE.pattern() == "ant/alive/*/*"
    assert keys.INFO.pattern(service="renderer") == "ant/svc/renderer/*/info"


def test_catalogue_is_complete_and_unique():
    templates = [k.template for k in keys.CATALOGUE]
    assert len(templates) == len(set(templates))
    assert keys.IO_OBSERVE in keys.CATALOGUE and keys.MISSION_EVENTS in keys.CATALOGUE
    from shared import schemas

    # Every schema a key names exists in shared.schemas, so the catalogue cannot drift from the models.
    for k in keys.CATALOGUE:
        for name in (k.request, k.reply):
            if name:
                assert hasattr(schemas, name), f"{k.template} names unknown schema {name}"


@pytest.mark.parametrize("a,b,expected", [
    ("ant/alive/*/*", "ant/alive/robot_io/x", True),
    ("ant/**", "ant/a/b/c", True),
    ("ant/*", "ant/a/b", False),
    ("ant/**/info", "ant/svc/r/i/info", True),
    ("ant/svc/*/i/info", "ant/svc/r/j/info", False),
    ("a/**", "a", True),
])
def test_key_expression_intersection(a, b, expected):
    assert intersects(a, b) is expected and intersects(b, a) is expected
