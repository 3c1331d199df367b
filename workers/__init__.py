"""Workers that run alongside training: zero-shot evaluation (`workers.evaluator`), ..."""
