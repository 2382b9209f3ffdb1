"""Where chunks of work run: in this process (``local``) or as Ray tasks (``ray``).

An executor maps a picklable function over picklable items and yields the results as
they finish (the caller saves each one at once, so a killed run resumes).
:class:`LocalExecutor` needs nothing; :class:`RayExecutor` needs Ray
(``pip install 'mitsuba-manifold[ray]'``). On a cluster, every node must see the
scene, manifold and database at the same paths (the results come back through Ray's
object store, so the output folder need only exist on the driver).
"""

from ...errors import UnavailableError

EXECUTORS = ("local", "ray")


class LocalExecutor:
    """Run the items one after another in this process."""

    name = "local"

    def map(self, fn, items):
        for item in items:
            yield fn(item)

    def close(self):
        pass


class RayExecutor:
    """Run each item as a Ray task (``max_retries`` re-runs a task whose worker died).

    Parameters
    ----------
    address : str, optional
        Ray cluster to join (``"auto"``, ``"ray://host:10001"``, ``"host:6379"``); default:
        the already initialised one, else a local cluster of ``num_cpus`` CPUs started here
        (and shut down by :meth:`close`).
    num_cpus : int, optional
        CPUs of a local cluster (default: all).
    cpus_per_task : int
        CPUs Ray reserves per task (so at most ``cpus / cpus_per_task`` tasks run at once on
        a node; each render still uses every core of its node through Dr.Jit's thread pool).
    max_retries : int
        Re-runs of a task after its worker process or node died.
    """

    name = "ray"

    def __init__(
        self, address=None, num_cpus=None, cpus_per_task=1, max_retries=3, runtime_env=None
    ):
        if int(cpus_per_task) < 1:
            raise UnavailableError(f"`cpus_per_task` must be >= 1, got {cpus_per_task}")
        if int(max_retries) < 0:
            raise UnavailableError(f"`max_retries` must be >= 0, got {max_retries}")
        self.address, self.num_cpus = address, num_cpus
        self.cpus_per_task, self.max_retries = int(cpus_per_task), int(max_retries)
        self.runtime_env = runtime_env
        self._started = False

    def _ray(self):
        try:
            import ray
        except ImportError:
            raise UnavailableError(
                "executor 'ray' needs Ray: pip install 'mitsuba-manifold[ray]' "
                "(or use the 'local' executor)"
            ) from None
        if not ray.is_initialized():
            kwargs = {"include_dashboard": False, "log_to_driver": False}
            if self.address:
                kwargs["address"] = self.address
            elif self.num_cpus:
                kwargs["num_cpus"] = int(self.num_cpus)
            if self.runtime_env:
                kwargs["runtime_env"] = self.runtime_env
            try:
                ray.init(**kwargs)
            except (ConnectionError, RuntimeError, ValueError) as e:
                raise UnavailableError(
                    f"cannot start or join the Ray cluster {self.address or '(local)'}: {e}"
                ) from None
            self._started = True
        return ray

    def start(self):
        """Start or join the cluster now (otherwise the first :meth:`map` does); returns self."""
        self._ray()
        return self

    def map(self, fn, items):
        ray = self._ray()
        items = list(items)
        remote = ray.remote(num_cpus=self.cpus_per_task, max_retries=self.max_retries)(fn)
        pending = [remote.remote(item) for item in items]
        try:
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                yield ray.get(done[0])
        finally:  # a failed chunk, Ctrl-C or a caller that stops: no task left rendering
            for ref in pending:
                ray.cancel(ref, force=True)

    def close(self):
        if self._started:
            import ray

            ray.shutdown()
            self._started = False


def make_executor(name="local", address=None, **kwargs):
    """``local`` or ``ray`` (``address`` and ``kwargs`` go to :class:`RayExecutor`)."""
    if name == "local":
        if address:
            raise UnavailableError("`address` is for the 'ray' executor")
        return LocalExecutor()
    if name == "ray":
        return RayExecutor(address=address, **kwargs)
    raise UnavailableError(f"`name` (the executor) must be one of {EXECUTORS}, got {name!r}")
