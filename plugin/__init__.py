"""Sylva."""
