"""moto's S3, served alone on loopback: ``python bench/moto_s3.py PORT`` (the benches' stand-in for S3).

``python -m moto.server`` sends every request through moto's dispatcher for all of AWS, which lists moto's package
folder (some 200 entries, each stat-ed) to recognise the service and holds one lock across that lookup. Here that
was 40% of moto's CPU per S3 request (a small PUT 3.4 → 2.0 ms, a GET 3.0 → 1.6 ms). A real S3 spends none of it on
the machine that runs the stages, so the cluster bench serves moto's S3 application alone: the same S3 behaviour
(conditional writes, ETags, listings), without the dispatcher (``bench/bench_dask.py --s3-server moto`` keeps
``python -m moto.server`` for comparison).
"""

from __future__ import annotations

import logging
import sys


def main() -> None:
    from moto.moto_server.werkzeug_app import create_backend_app
    from werkzeug.serving import run_simple

    logging.getLogger("werkzeug").setLevel(logging.ERROR)
    run_simple("127.0.0.1", int(sys.argv[1]), create_backend_app("s3"), threaded=True)


if __name__ == "__main__":
    main()
