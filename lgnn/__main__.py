"""`python -m lgnn ...`: the `lgnn` command (`lgnn.cli.entry`)."""

from lgnn.cli import entry

entry()
