"""Learning side of TABX-UED: learners, curricula (DR, PLR, Robust PLR, ACCEL, SFL), level
generation and mutation, and level scores (`ued.scores`)."""
