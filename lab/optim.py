"""Adam, the optimiser of the lab's trainers: the SAC experts (lab/sac.py) and the
baselines BC and GAIL (lab/baselines.py), as their reference implementations use it. The
learner itself uses nets.RMSProp (Appendix B)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Adam:
    """Adam (Kingma & Ba, 2015, Algorithm 1).

        m     <- beta1 m + (1 - beta1) g                     (first moment)
        v     <- beta2 v + (1 - beta2) g^2                   (second moment)
        param <- param - lr m_hat / (sqrt(v_hat) + eps),     m_hat = m / (1 - beta1^t),
                                                             v_hat = v / (1 - beta2^t)

    The bias corrections are folded into two scalars, as in Sec. 2 of the paper:
    lr_t = lr sqrt(1 - beta2^t) / (1 - beta1^t) and eps_t = eps sqrt(1 - beta2^t), so
    that the update is lr_t m / (sqrt(v) + eps_t), the same number as PyTorch's
    `torch.optim.Adam` computes, in two array passes fewer. Defaults are PyTorch's.
    `t` counts the steps taken; it is part of the state, so a resumed run continues
    with the same bias corrections.
    """

    beta1: float = 0.9
    beta2: float = 0.999
    eps: float = 1e-8
    t: int = 0
    first_moment: dict[str, np.ndarray] = field(default_factory=dict)
    second_moment: dict[str, np.ndarray] = field(default_factory=dict)

    def step(self, params: dict[str, np.ndarray], grads: dict[str, np.ndarray], lr: float):
        self.t += 1
        correction2 = 1.0 - self.beta2**self.t
        lr_t = lr * correction2**0.5 / (1.0 - self.beta1**self.t)
        eps_t = self.eps * correction2**0.5
        for name, grad in grads.items():
            param = params[name]
            grad = np.asarray(grad, dtype=param.dtype)  # a float64 gradient stays float32 work
            m = self.first_moment.setdefault(name, np.zeros_like(param))
            v = self.second_moment.setdefault(name, np.zeros_like(param))
            m *= self.beta1
            m += (1.0 - self.beta1) * grad
            v *= self.beta2
            v += (1.0 - self.beta2) * (grad * grad)
            denominator = np.sqrt(v)
            denominator += eps_t
            param -= lr_t * m / denominator

    def state(self, prefix: str) -> dict[str, np.ndarray]:
        return {
            f"{prefix}/t": np.array(self.t),
            **{f"{prefix}/m/{name}": value for name, value in self.first_moment.items()},
            **{f"{prefix}/v/{name}": value for name, value in self.second_moment.items()},
        }

    def load_state(self, arrays, prefix: str) -> None:
        self.t = int(arrays[f"{prefix}/t"])
        for letter, moments in (("m", self.first_moment), ("v", self.second_moment)):
            start = f"{prefix}/{letter}/"
            moments.clear()
            moments.update(
                {
                    key.removeprefix(start): np.array(arrays[key])
                    for key in arrays
                    if key.startswith(start)
                }
            )
