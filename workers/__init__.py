"""Who runs what, where. At the top, the run's lifecycle: `workers.train.train` (the library
entry of `tabx train`), the driver interface (`workers.driver`), the one training loop
(`workers.training_loop`), one UED step (`workers.ued_step`), resume (`workers.resume`), the
local driver (`workers.local`) and progress lines (`workers.progress`). `workers.roles` holds
what runs in-process or inside actors (learner, Explorer, Evaluator, level service),
`workers.ray` the placement on Ray, `workers.sweep` the sweeps."""
