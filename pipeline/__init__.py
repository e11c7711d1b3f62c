"""Stages that turn a survey into corrected images, 3D products and reports."""
