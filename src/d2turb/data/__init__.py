"""d2turb.data"""
