"""Evaluation beside the fitting core: scores against ground truth (``metrics``), the sample data's
shape folders (``sample_data``) and synthetic shapes with known edges (``shapes``).

It uses ``core`` (to read clouds) and nothing of the service; ``core`` never imports it.
"""
