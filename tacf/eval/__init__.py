"""Evaluation toolkit: dataset loaders, OTB-protocol metrics, tracker registry, frame loop, reports.

    from tacf.eval.datasets import load_sequences
    from tacf.eval.trackers import make_tracker
    from tacf.eval.runner import track_sequence
    from tacf.eval.metrics import success_curve, precision_curve

Submodules are imported on demand so that `tacf.cli` stays cheap.
"""
