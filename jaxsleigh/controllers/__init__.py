"""Feedback laws from the literature, and actuators between a law and the plant.

Every law here is a controller in the sense of `jaxsleigh.model.controller`: a small pytree ``law`` with
``u = law(q, v)`` (or ``law(q, v, t)`` for a time-varying law, which says ``time_varying = True``). Each
module cites the paper its law comes from and writes its equations once, with their numbers; its
``needs`` says what of the plant the law must know (the paper's law needs nothing: its selling point).
"""
