"""Training a policy: the trainer of one run (:mod:`.train`), the one optimisation step of solo and stacked runs
(:mod:`.train_step`), runs trained as one stacked network (:mod:`.train_stack`, :mod:`.stack_optim`). Above the
policy families, below the algorithm."""
