"""twist_models: the building blocks of the world models (RSSM, encoders, teacher, student,
read-out, losses, actor-critic, checkpoints) and, in ``stages``, the pipeline that assembles
them."""
