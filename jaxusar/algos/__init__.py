"""Learners, one file each, written against jaxusar.core (each file holds only its own math)."""
