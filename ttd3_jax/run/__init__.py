"""A training run (layer 4): its spec (``spec``: presets, ``config.json``), the envs it can train
on (``tasks``), its directory on disk (``rundir``; ``status``: the lock and ``state.json``), the
Python loop around the compiled epochs (``loop``), orbax checkpoints (``checkpoint``), the
compilation cache (``cache``), the memory check (``memory``), devices (``sharding``) and its
tables and plots (``report``)."""
