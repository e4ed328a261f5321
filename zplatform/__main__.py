"""``python -m zplatform``: the ``zplatform`` command (:func:`zplatform.cli.main.main`)."""

import sys

from .cli.main import main

sys.exit(main())
