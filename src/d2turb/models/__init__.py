"""d2turb.models"""
