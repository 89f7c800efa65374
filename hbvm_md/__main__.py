"""``python -m hbvm_md``: the ``hbvm-md`` command line."""
import sys

from .cli import main

sys.exit(main())
