"""Images with ground truth: phantom files (phantom) rendered into complex B-scan or volume
sequences (render).
"""
