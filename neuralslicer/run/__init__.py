"""What runs the paper's steps: a run of the chain and its records, beside the steps themselves.

``step_table`` (every step once, as data), ``pipeline`` (the chain written once), ``in_process`` (the chain in this
process), ``collision_policy`` (what a colliding print asks for next), ``field_step`` (the field's record for each
method), ``preflight`` (the checks before a run), ``run_metrics``, ``provenance``, ``outputs``, ``report`` and
``report_embed`` (a run's figures, record and files), ``compare`` (two runs' metrics side by side). The paper's
objects and steps are the other folders and modules of ``neuralslicer/``.
"""
