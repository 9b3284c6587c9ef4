"""twist_models: world models (RSSM, encoders, teacher, student, losses, actor-critic, checkpoints).

Filled in by the world-models work; the package exists so the distribution's layout is final.
"""
