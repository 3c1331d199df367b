"""Who runs what, where: the driver interface (`workers.driver`), the local driver
(`workers.local`), the workers it wires (LevelService, LearnerWorker, Explorer, Evaluator) and
`workers.train.train`, the library entry of `tabx train`."""
