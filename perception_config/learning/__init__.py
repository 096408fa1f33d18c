"""Offline learning: training, validation and seed selection, evaluation studies, Ray workers, and
fitting the pick-success score."""
