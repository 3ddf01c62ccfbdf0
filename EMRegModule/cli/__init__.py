"""The ``emreg`` subcommands, one module per family; :mod:`.args` turns arguments into settings, ports and OUT."""
