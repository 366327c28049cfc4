"""``python -m torch_polylap.cli``: the ``polylap`` command, ended as the console script ends it
(one line and ``128 + signal`` for a signal up to the end of the process)."""

from _polylap_launcher import main

main()
