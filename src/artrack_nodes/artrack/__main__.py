"""`python -m artrack ...` is the `artrack` command."""

import sys

from .cli import main

sys.exit(main())
