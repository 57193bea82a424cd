"""``python -m crfedit`` runs the command line."""

from .cli import main

main()
