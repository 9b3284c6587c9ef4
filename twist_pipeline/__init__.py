"""twist_pipeline: the stages that join the dataset, the simulator and the models, each a
library function that a console command calls: ``collect`` (the state teacher writing D),
``distil`` (the student from D), ``baselines`` (the paper's offline image baselines on D),
``evaluation`` (agents on held-out scenes; ``factors`` one deployment factor at a time,
``learning_curve`` a run's snapshots) and ``report`` (all of them for tasks x seeds).
``acting`` adapts a teacher or a student to act in the simulator, for collection and
evaluation alike; ``runlog`` is what every stage's run folder shares; ``statistics`` and
``curves`` are the figures and plots the stages report."""
