"""Stereo: pair selection and rectification, dense matching, triangulation, fusion."""
