"""``python -m labelaudit.cli`` runs the command line."""

from labelaudit.cli import main

if __name__ == "__main__":  # not when a doctest collector imports it
    main()
