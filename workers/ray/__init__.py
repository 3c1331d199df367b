"""Everything that places a run on Ray: starting or joining a cluster, the actors around the
roles, their handles, the one actor manager, learner restarts, the durable level service, the
learner group, the schedules (sequential, asynchronous, continuous), stats, the live view and
`tabx eval --ray`. Outside sweeps, this is the only package that imports Ray."""
