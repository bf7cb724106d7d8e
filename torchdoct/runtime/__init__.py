"""The ground floor of the process, imported by every stage and importing none of them (nothing here loads
torch at import time, so the torch-free classify path may use it): :mod:`.threads` (the threading policy:
one torch thread per worker, parallel work over independent pieces), :mod:`.interrupt` (Ctrl-C, SIGTERM
and closed pipes at the entry points), :mod:`.device` (the ``--device`` check), :mod:`.resources` (the one
resource check before the work of every command) and :mod:`.machine` (the machine record of every
benchmark)."""
