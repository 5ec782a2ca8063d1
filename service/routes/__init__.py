"""One router per resource: scenes, jobs (refinement, added later), health/info/metrics."""
