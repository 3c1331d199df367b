"""The roles of a run: the learner, the Explorer, the Evaluator and the level service. Each is a
plain class that runs in the driver's process (the local driver) or inside a Ray actor
(`workers.ray.actors` wraps them); none of them imports Ray."""
