"""The ``emreg`` command: :mod:`.main` holds the table of commands, :mod:`.options` declares their arguments, and one
module per command family parses, calls the pipeline and prints; :mod:`.args` turns arguments into settings, ports
and OUT."""
