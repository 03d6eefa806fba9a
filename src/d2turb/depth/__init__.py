"""d2turb.depth"""
