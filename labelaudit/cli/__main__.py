"""``python -m labelaudit.cli`` runs the command line."""

from labelaudit.cli import main

main()
