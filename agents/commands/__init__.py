"""The ``bimp`` commands, one module per command: each ``main(argv) -> int`` parses its arguments (argparse lives
here and in :mod:`bimp.agents.cli` only) and calls the library, which never imports this package. The helpers the
commands share: :mod:`.args`."""
