from sb3_mtte.mtsacte.mtsacte import MTSACTE
from sb3_mtte.mtsacte.policies import MlpPolicy, MTSACTEPolicy

__all__ = ["MTSACTE", "MTSACTEPolicy", "MlpPolicy"]
