"""The study's statistics, apart from any step or flow: paired arm differences with hierarchical-bootstrap
intervals, the design's power (MDD), and the success-vs-steps endpoint. Pure numpy, pandas and pydantic
(no store, step or flow), so a script or notebook can recompute a report's numbers from its episode
records alone."""
