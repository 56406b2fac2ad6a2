"""The command lines (layer 6): ``train``, ``evaluate``, ``export`` parse and check their
arguments, show the package's log (``console``) and call the run and interop layers.  Run them
as ``python -m ttd3_jax.train|evaluate|export``."""
