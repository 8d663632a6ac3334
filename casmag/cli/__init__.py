"""The command line: main.py (the commands, entry point casmag.cli.main:main), sweep.py
(casmag sweep) and tools.py (options, exit codes, how every solving command ends)."""
