"""``python -m edgepose.cli``."""

from edgepose.cli import main

main()
