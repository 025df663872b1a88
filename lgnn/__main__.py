"""`python -m lgnn ...`: the `lgnn` command (`lgnn.cli.main`)."""

import sys

from lgnn.cli import main

sys.exit(main())
