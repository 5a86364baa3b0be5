"""The cell's services, one folder each (docs/design.md, "Layout")."""

import sys

# `python -m services.NAME` (the demo's process cell): a stop before the service runs is a clean exit
# (common/runtime/early.py). While Python locates the module, argv[0] is "-m".
if sys.argv[:1] == ["-m"]:
    from common.runtime.early import exit_cleanly_until_started

    exit_cleanly_until_started()
