"""The pareto store's tests' task program, as a file."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.support.tasks import TINY


@pytest.fixture
def task_file(tmp_path: Path) -> Path:
    p = tmp_path / "tiny.toml"
    p.write_text(TINY)
    return p
