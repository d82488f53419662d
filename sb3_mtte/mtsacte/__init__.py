from sb3_mtte.mtsacte.callbacks import NegativeTransferLogCallback
from sb3_mtte.mtsacte.mtsacte import MTSACTE
from sb3_mtte.mtsacte.policies import EmbeddingActor, MlpPolicy, MTSACTEPolicy

__all__ = ["MTSACTE", "EmbeddingActor", "MTSACTEPolicy", "MlpPolicy", "NegativeTransferLogCallback"]
