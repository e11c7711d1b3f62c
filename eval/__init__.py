"""Measuring: the survey simulator, colour and depth metrics, diagnosis and reports."""
