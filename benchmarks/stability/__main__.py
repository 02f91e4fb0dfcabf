"""``python -m benchmarks.stability``: the numerical stability suite (see
``benchmarks.stability.cli``)."""

import sys

from benchmarks.stability.cli import main

sys.exit(main())
