"""``python -m accel_bayes.cli`` is the ``accel-bayes`` command (as is ``python -m accel_bayes``)."""
import sys

from . import main

sys.exit(main())
