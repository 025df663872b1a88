"""A model of your own, for `lgnn benchmark --add-model docs/examples/own_lgnn.py:SPEC`.

It is lgnn's own LGNN under another name: a model of LGNN's size and cost, so the
path from a model file to its leaderboard row can be timed on a model that learns
what the built-in ones learn. Write yours the same way: a `ModelSpec` (docs/models.md,
"Your own model") with a name no other model has.
"""

import dataclasses

from lgnn.learn.models import get_spec

SPEC = dataclasses.replace(get_spec("lgnn"), name="own-lgnn")
