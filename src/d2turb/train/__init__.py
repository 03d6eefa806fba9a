"""d2turb.train"""
