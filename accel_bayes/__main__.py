"""``python -m accel_bayes`` is the ``accel-bayes`` command."""
import sys

from .cli import main

sys.exit(main())
