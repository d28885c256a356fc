"""Seed 004's script listings as printed (Figures 2, 3, 5, 6), shared by the tests."""

FIG5 = """\
dim Q_EXH_BP_R
Q_EXH_BP_R=1
dim R_EXH_BP_R
R_EXH_BP_R=0.1
dim X_hat_Prev_EXH_BP_R
X_hat_Prev_EXH_BP_R=0
dim P_Prev_EXH_BP_R
P_Prev_EXH_BP_R=1
dim K_EXH_BP_R
K_EXH_BP_R=0.1
dim X_hat_EXH_BP_R
X_hat_EXH_BP_R=0
dim P_EXH_BP_R
P_EXH_BP_R=1

//Constants
Q_EXH_BP_R = 4*pow(10,-6)
R_EXH_BP_R = pow(10,-4)
"""

FIG6 = """\
// EXH_BP_R Kalman Filter
public EXH_BP_R_Kalman

//calculations
K_EXH_BP_R = P_EXH_BP_R * pow((P_EXH_BP_R + R_EXH_BP_R),-1)

X_hat_EXH_BP_R = X_hat_Prev_EXH_BP_R + K_EXH_BP_R * (EXH_BP_R - \\
X_hat_Prev_EXH_BP_R)

P_EXH_BP_R = (1 - K_EXH_BP_R) * P_Prev_EXH_BP_R * (1 - K_EXH_BP_R) \\
+ K_EXH_BP_R * R_EXH_BP_R * K_EXH_BP_R

EXH_BP_R_Kalman = X_hat_EXH_BP_R

//cyclic updates
X_hat_Prev_EXH_BP_R = X_hat_EXH_BP_R

P_Prev_EXH_BP_R = P_EXH_BP_R + Q_EXH_BP_R
"""

FDV = "[init]\n" + FIG5 + "\n[formulas]\n" + FIG6

FIG2 = """\
#
# in_variable samples rate (FAS/MED/SLO) statistical_variable
#
#####
X_hat_EXH_BP_L 1 MED a_X_hat_EXH_BP_L_lm. # 0.1s avg 10Hz
P_EXH_BP_L 1 MED a_P_EXH_BP_L_lm. # 0.1s avg 10Hz
X_hat_EXH_BP_R 1 MED a_X_hat_EXH_BP_R_lm. # 0.1s avg 10Hz
P_EXH_BP_R 1 MED a_P_EXH_BP_R_lm. # 0.1s avg 10Hz
"""

#: Figure 3 exactly as printed, including the lost digit in ``([none] - K_EXH_BP_R)``.
FIG3_PRINTED = """\
# *****
# EXH_BP_R Kalman Filter
# *****
#Label units format initial_value interval/event hst_flag tolerance
# parameters
X_hat_prev_EXH_BP_R none 3 0 MED OFF 1.0
a_X_hat_EXH_BP_R_lm.FV

Q_Gain_EXH_BP_R none 7 0.05 MED OFF 1.0
4[none] * @pow(10[none],-6[none])

P_prev_EXH_BP_R none 3 1 MED OFF 1.0
a_P_EXH_BP_R_lm.FV + Q_Gain_EXH_BP_R

R_Gain_EXH_BP_R none 7 1.0 MED OFF 1.0
1[none] * @pow(10[none],-4[none])

# Final estimation conversion to correct units
EXH_BP_R_kalman MM_H2O 3 1 MED OFF 1.0
{X_hat_EXH_BP_R}

# Calculations
K_EXH_BP_R none 3 0.1 MED OFF 1.0
P_EXH_BP_R * @pow((P_EXH_BP_R + R_Gain_EXH_BP_R),-1[none])

X_hat_EXH_BP_R none 3 0 MED OFF 1.0
{X_hat_EXH_BP_R + K_EXH_BP_R * (EXH_BP_R - X_hat_EXH_BP_R)}

P_EXH_BP_R none 3 1 MED OFF 1.0
{([none] - K_EXH_BP_R) * P_prev_EXH_BP_R * ([none] - K_EXH_BP_R)\\
+ K_EXH_BP_R * R_Gain_EXH_BP_R * K_EXH_BP_R}
"""

#: The one correction the issue names: ``([none] - K)`` means ``(1[none] - K)``.
FIG3 = FIG3_PRINTED.replace("([none] - K_EXH_BP_R)", "(1[none] - K_EXH_BP_R)")

#: Figure 2's lines for the right bank only (the left bank's labels are not in Figure 3).
FIG2_R = "\n".join(line for line in FIG2.splitlines() if "_L " not in line) + "\n"
