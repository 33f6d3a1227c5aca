"""The field's safe-sampling methods, each a controller on the shared sampler
(:mod:`~workbench.sampling.methods.sampler`: MPPI batches with a per-sample projection or a
DCBF cost in the kernel).

Every controller follows the workbench's protocol (``initial_state``, ``step(state, x, rng)``
returning ``(state, u, info)``, ``set_scene``) and its step info exposes ``stats``
(:class:`~workbench.sampling.step_stats.StepStats`), so that studies compare them on equal terms.
"""
