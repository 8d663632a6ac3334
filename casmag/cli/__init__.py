"""The command line: main.py (the commands, entry point casmag.cli.main:main) and tools.py
(options, exit codes, how every solving command ends)."""
