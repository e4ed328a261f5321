"""``python -m zplatform``: the ``zplatform`` command (:func:`zplatform.cli.main`)."""

import sys

from .cli import main

sys.exit(main())
