"""Benchmarks and peers (Intel Embree through embreex). Uses jrt's public API only.

The benchmarks own their process, so they keep freed memory for the next call
(``jrt.tune_malloc``), as the ``jrt`` command does.
"""

import jrt

jrt.tune_malloc()
