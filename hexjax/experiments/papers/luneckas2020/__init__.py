"""Luneckas 2020: the experiment matrix with and without the tactile method (`matrix`), the analytic
positional-error model (`error_model`, Eqs. 8-14), and the LSTM error predictor (`dataset`, `predictor`,
Sect. 2.6), all over the walks of `walks`."""
