"""The user docs stay in step with the code they describe."""

import re
from pathlib import Path

from service.config import Settings

DOCS = Path(__file__).resolve().parents[1] / "docs"


def test_operations_doc_lists_every_setting():
    """docs/operations.md's settings table names every ``OMNISPLAT_*`` variable of service.config.Settings."""
    listed = set(re.findall(r"`OMNISPLAT_([A-Z0-9_]+)`", (DOCS / "operations.md").read_text()))
    assert not {k for k in Settings.model_fields if k.upper() not in listed}
