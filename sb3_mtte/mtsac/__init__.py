from sb3_mtte.mtsac.mtsac import MTSAC
from sb3_mtte.mtsac.policies import IndependentPolicy, MlpPolicy, MultiHeadPolicy, SoftModularPolicy

__all__ = ["MTSAC", "IndependentPolicy", "MlpPolicy", "MultiHeadPolicy", "SoftModularPolicy"]
