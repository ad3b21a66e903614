"""``python -m deliffas`` = the ``deliffas`` command (also what ``torchrun -m deliffas`` runs)."""

from deliffas.cli import main

raise SystemExit(main())
