"""d2turb.sim"""
