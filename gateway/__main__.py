"""``python -m gateway``: the same entry point as the ``gateway`` command."""

from gateway.cli import main

main()
