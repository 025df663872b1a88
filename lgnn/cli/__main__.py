"""`python -m lgnn.cli ...`: the `lgnn` command (`lgnn.cli.main`)."""

import sys

from lgnn.cli import main

if __name__ == "__main__":  # not on import (the architecture tests import every module)
    sys.exit(main())
