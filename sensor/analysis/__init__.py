"""Analysis: closed-form statistics of the spike models (oracles) and the realism report that holds a
real recording against each model.
"""
