"""Evaluation of agents: batched episodes, success rates with confidence intervals, tables beside the paper."""
