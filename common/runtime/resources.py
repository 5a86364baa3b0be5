"""Where the files that ship with Cadence are: the example task, its planned sets and the deploy
templates. In a checkout they are ``deploy/``; in an installed wheel, ``cadence/deploy/files/``
(pyproject's force-include). Nothing else may build a path from the checkout's layout, or an installed
``cadence`` breaks."""

from __future__ import annotations

from pathlib import Path

_ROOT = Path(__file__).resolve().parents[2]
DEPLOY = next(
    (p for p in (_ROOT / "cadence" / "deploy" / "files", _ROOT / "deploy") if p.is_dir()), _ROOT / "deploy"
)
EXAMPLE_TASK = DEPLOY / "tasks" / "box_filling.toml"
FOXGLOVE_LAYOUT = DEPLOY / "foxglove" / "cadence.layout.json"
SHIPPED_SETS = DEPLOY / "sets"  # planned sets as data, by content hash (common/trajectory/shipped.py)
