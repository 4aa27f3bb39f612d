"""Checks of a task against the experiment's conventions: what ``sdp check-task`` runs.

This layer sits above the tasks, the data, the policies, the rollout and the optimizers, and uses them all:
``contract`` (the model's conventions, the oracle replay, the memorizer at every (T_h, T_a) the pipelines
use), ``timing`` (is the optimum well-posed for a policy that does not see time) and ``noise`` (how much
chunk error each conversion forgives). ``sdp_cli.tasks`` itself imports nothing above it (tests/test_imports.py).
Moved here from ``sdp_cli.tasks.contract`` / ``.timing`` / ``.noise``.
"""
