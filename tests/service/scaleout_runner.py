"""A registration function for the scale-out tests (``PWLREG_RUNNER``): the slow registration of
:mod:`tests.service.runners`, then one line in the ledger file ``PWLREG_TEST_LEDGER`` for every
registration that ran to completion: the digest of its reference image and the process id.

The line is written when the registration returns, before the worker stores the results and
ends the job: a worker killed between the two leaves the line of an attempt that is run again
(the job still ends once). The tests kill a worker only before its line is written."""

from __future__ import annotations

import hashlib
import os
from typing import Any

import numpy as np

from tests.service.runners import slow_register


def digest(image: np.ndarray) -> str:
    """What the ledger records of a decoded reference image."""
    return hashlib.sha1(np.ascontiguousarray(image).tobytes()).hexdigest()


def ledger_register(reference: Any, moving: Any, points: Any = None, options: Any = None,
                    progress: Any = None) -> Any:
    result = slow_register(reference, moving, points=points, options=options, progress=progress)
    line = f"{digest(reference)} {os.getpid()}\n".encode()
    fd = os.open(os.environ["PWLREG_TEST_LEDGER"], os.O_WRONLY | os.O_APPEND | os.O_CREAT)
    try:
        os.write(fd, line)  # one small append: whole lines even from several processes
    finally:
        os.close(fd)
    return result
