"""``python -m arena_common.cli`` runs the ``arena`` command."""

from arena_common.cli import main

main()
