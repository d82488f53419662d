from sb3_mtte.mtsac.moore import MOOREPolicy
from sb3_mtte.mtsac.mtsac import MTSAC
from sb3_mtte.mtsac.paco import PaCoPolicy
from sb3_mtte.mtsac.policies import IndependentPolicy, MlpPolicy, MultiHeadPolicy, SoftModularPolicy

__all__ = [
    "MTSAC",
    "IndependentPolicy",
    "MOOREPolicy",
    "MlpPolicy",
    "MultiHeadPolicy",
    "PaCoPolicy",
    "SoftModularPolicy",
]
