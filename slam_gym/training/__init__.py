"""Training learned interface policies: hyper-parameters, runs, seeds (``slam-gym train``)."""
