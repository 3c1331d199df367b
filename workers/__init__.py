"""Who runs what, where: the driver interface (`workers.driver`), the training loop every run
goes through (`workers.training_loop`), one UED step (`workers.ued_step`), the local driver
(`workers.local`), the workers it wires (LevelService, LearnerWorker, Explorer, Evaluator) and
`workers.train.train`, the library entry of `tabx train`."""
