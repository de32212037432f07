"""The papers' experiments, one folder a paper (configs/experiments/*.yaml name their modules here): Chen 2019
(support planning on the rugged patch, the incenter), Luneckas 2020 (the tactile matrix, the error model and
predictor), Yu 2019 (the CPG's network, steps and ditches), Zhao 2018 (Table 2, random fields, the closed loop)."""
