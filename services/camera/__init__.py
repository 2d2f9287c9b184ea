"""The camera service (the endoscope view): see services/camera/service.py."""
