"""The README's key table is generated from shared/keys.py; this keeps the two from drifting."""

from pathlib import Path

from shared import keys

README = Path(__file__).resolve().parents[3] / "README.md"


def test_readme_lists_every_key_expression_and_the_two_commands():
    text = README.read_text()
    assert text.index("make demo") < text.index("## Architecture")
    assert "make test" in text
    for k in keys.CATALOGUE:
        assert f"`{k.template}`" in text, f"README lacks {k.template}"
