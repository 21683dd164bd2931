"""Run outputs: collect what a pipeline run produced and score it against ground truth."""
