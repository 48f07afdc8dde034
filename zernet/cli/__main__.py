"""``python -m zernet.cli``: the ``zernet`` command, as ``torchrun -m zernet.cli`` starts it on each process."""

import sys

from zernet.cli import main

sys.exit(main())
