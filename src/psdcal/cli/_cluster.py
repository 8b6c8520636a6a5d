"""``--scheduler``: run a study's trials on a Dask cluster instead of local processes."""
from __future__ import annotations

from contextlib import contextmanager

import click

from psdcal.errors import InputError

def scheduler_option(f):
    """The ``--scheduler ADDRESS`` option of the commands that run many trials."""
    return click.option(
        "--scheduler", default=None, metavar="ADDRESS",
        help="Run the trials on a Dask cluster (a scheduler address such as tcp://10.0.0.5:8786; "
             "needs `pip install 'psdcal[cluster]'`, and psdcal installed on the workers). "
             "The tables are the same as on one machine.")(f)


@contextmanager
def trial_executor(scheduler: str | None):
    """A ``concurrent.futures.Executor`` on the Dask scheduler at ``scheduler`` (None: yields None).

    Raises
    ------
    InputError
        ``distributed`` is not installed, or the scheduler cannot be reached.
    """
    if scheduler is None:
        yield None
        return
    try:
        import distributed
    except ImportError:
        raise InputError("needs the 'distributed' package: pip install 'psdcal[cluster]'",
                         field="scheduler") from None
    try:
        # the connect timeout is Dask's own setting (distributed.comm.timeouts.connect, 30 s by default)
        client = distributed.Client(scheduler, set_as_default=False)
    except (OSError, TimeoutError, ValueError, TypeError) as exc:
        raise InputError(f"cannot reach the Dask scheduler at {scheduler!r} ({type(exc).__name__}: {exc})",
                         field="scheduler") from None
    with client:
        yield client.get_executor()


@contextmanager
def study_executor(workers: int | None, scheduler: str | None):
    """The executor of a study's tasks: the Dask cluster at ``scheduler``, else ``workers`` local processes.

    Yields None (run in this process) when neither asks for more than one process.
    """
    if scheduler is not None:
        with trial_executor(scheduler) as executor:
            yield executor
        return
    if workers is None or workers <= 1:
        yield None
        return
    import concurrent.futures as cf

    with cf.ProcessPoolExecutor(max_workers=workers) as executor:
        yield executor
