"""The spike models: the ELSSim detector effects as pure functions, the step (reference) models, the
event-driven fast kernels, and the model registry.
"""
