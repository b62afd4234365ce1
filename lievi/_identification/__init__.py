"""System identification: `fit_system`, `fit_inertia` and their report `SystemFit`.

One job per module: `_fit` (the two entry points), `_arguments` (argument checks),
`_parametrisation` (unconstrained coordinates of each fitted leaf), `_start` (the default
initial inertia), `_problem` (model, residuals, loss, goodness of fit), `_schedule` (the
batch driver), `_optimizer` (the per-body optimiser state machines), `_identifiability`
and `_result`.
"""
