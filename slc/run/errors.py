"""Errors of a run that the command line reports in one line (exit status 2)."""
from __future__ import annotations

from slc.core.check import CheckError


class ExperimentError(ValueError):
    """Bad experiment input: unknown experiment, bad option, unreachable cluster (one-line message)."""


class JobsFailed(RuntimeError):
    """Some jobs still failed after their retries (one-line summary; exit status 1: a run error,
    not bad input)."""


def raise_fatal(res: dict) -> None:
    """Stop the run on a check-mode error reported by a job (``{"fatal": message}``)."""
    if "fatal" in res:
        raise CheckError(res["fatal"])
