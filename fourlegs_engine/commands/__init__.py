"""The ``fourlegs`` command line: the only place argparse lives.

:mod:`.main` builds the parser and maps errors to exit codes; :mod:`.options` holds the options several
commands share and their translation into the library's option dataclasses; every other module is one
command family (``register(subparsers)``). Domain packages never import this package.
"""
