"""``python -m f2l.cli ...``: the ``f2l`` command."""

from f2l.cli.app import main

main()
