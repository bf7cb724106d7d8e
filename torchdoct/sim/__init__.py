"""The simulator: scene files and their validation (config, scenes), the plan of what runs (plan),
the batched point simulator (simulate), DOCT metrics of [..., frames] tensors (metrics), closed forms
(theory) and the decorrelation signature (signature).
"""
