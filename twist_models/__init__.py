"""twist_models: the building blocks of the world models (RSSM, encoders, teacher, student,
read-out, losses, actor-critic, checkpoints), which know neither the simulator nor the
pipeline (:mod:`twist_pipeline`) that assembles them."""
