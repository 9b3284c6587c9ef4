"""The pipeline's stages, each a library function that a console command calls: ``collect``
(the state teacher writing D), ``distil`` (the student from D), ``baselines`` (the paper's
offline image baselines on D), ``evaluation`` (agents on held-out scenes; ``factors`` one
deployment factor at a time, ``learning_curve`` a run's snapshots) and ``report`` (all of them
for tasks x seeds). ``runlog`` is what every stage's run folder shares. The modules
beside this package are the building blocks the stages assemble."""
