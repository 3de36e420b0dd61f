"""The README's dataflow diagram and key table are generated from shared/keys.py; this keeps them in step."""

from pathlib import Path

import pytest

from shared import keys

README = Path(__file__).resolve().parents[3] / "README.md"
SERVICES = {"robot_io", "mapper", "reconstructor", "renderer", "planner", "gateway"}


def test_readme_shows_the_two_commands_first_and_the_generated_topology():
    text = README.read_text()
    assert text.index("make demo") < text.index("## Architecture")
    assert "make test" in text
    assert keys.render_readme(text) == text, "README is stale: run `python -m shared.keys --write README.md`"
    for k in keys.CATALOGUE:
        assert f"`{k.template}`" in text, f"README lacks {k.template}"


def test_every_key_names_real_services_and_every_data_key_has_a_consumer_or_says_why():
    for k in keys.CATALOGUE:
        assert k.owner in SERVICES | {"*"}, k.template
        assert set(k.consumers) <= SERVICES, k.template
        assert k.owner not in k.consumers, k.template
    # Publications nobody in the system subscribes to exist for outside observers (a dashboard, a
    # recorder, rviz); they are the only keys allowed without a consumer.
    orphans = {k.template for k in keys.CATALOGUE if not k.consumers and k.usage != keys.Usage.PUBLICATION}
    assert not orphans


def test_render_readme_refuses_a_readme_without_its_blocks():
    with pytest.raises(ValueError, match="dataflow"):
        keys.render_readme("no blocks here")
