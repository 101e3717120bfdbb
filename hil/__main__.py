"""``python -m hil`` entry point."""

import sys

from hil.cli import main

sys.exit(main())
