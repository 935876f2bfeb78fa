"""``python -m deft_gym.cli``: the ``deft-gym`` command."""

import sys

from deft_gym.cli.main import main

sys.exit(main())
