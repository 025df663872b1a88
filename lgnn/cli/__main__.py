"""`python -m lgnn.cli ...`: the `lgnn` command (`lgnn.cli.entry`)."""

from lgnn.cli import entry

if __name__ == "__main__":  # not on import (the architecture tests import every module)
    entry()
