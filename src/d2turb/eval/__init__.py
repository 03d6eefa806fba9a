"""d2turb.eval"""
