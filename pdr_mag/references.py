"""The source documents the library follows, each cited elsewhere by its key and the equation or section
(``[Liu2018] eqs. 7–16``).

[Long2013]
    Long Li, Zhang He, Ding Libo: *Ellipsoid fitting compensation algorithm of 3-axis magnetometer based
    on maximum likelihood estimator*.  Journal of Nanjing University of Science and Technology 37(5):716–719,
    2013.  (龙礼, 张合, 丁立波. 三维磁传感器最大似然估计椭球拟合补偿算法. 南京理工大学学报.)
    The lumped error model ``H_m = S·H_i + b + ε`` (eqs. 3–4), its ellipsoid (eqs. 4–7, the likelihood
    eq. 7), the radial objective solved by Newton's method (eq. 10), the alignment by a least-squares
    rotation (eq. 12): :mod:`pdr_mag.calibration.ml`, :mod:`~pdr_mag.calibration.geometry`,
    :mod:`~pdr_mag.calibration.alignment`, :mod:`pdr_mag.sim.sensor_model`.
[Zhong2017]
    Zhong Hao, Zhang Weiguo, Liu Xiaoxiong: *Research on calibration methods of three-axis magnetometer
    based on vector norm estimation*.  Chinese Journal of Sensors and Actuators, 2017, no. 10,
    doi:10.3969/j.issn.1004-1699.2017.10.010.  (鐘浩, 章衛國, 劉小雄. 基于模值估计的三轴磁力计标定方法研究.
    传感技术学报.)  The 9-parameter model with the field norm as a parameter (§2.1, eq. 9), the two-step
    initial value (§2.3, eqs. 10–13) and its Levenberg–Marquardt refinement (eq. 14):
    :mod:`pdr_mag.calibration.twostep`, :mod:`pdr_mag.calibration.ml`.
[Liu2018]
    Liu Yu, Chen Yongwei, Lu Yongle, Ding Qixing, Li Yao: *Research on error compensation and calibration
    of magnetometer based on least square method*.  Navigation Positioning and Timing, 2018, no. 1,
    pp. 17–21, doi:10.19306/j.cnki.2095-8110.2018.01.003.  (刘宇, 陈永炜, 路永乐, 丁其星, 李瑶.
    基于最小二乘法的磁力计误差补偿与校准. 导航定位与授时.)  The hard-iron offset by linear least squares
    (eqs. 2–16), the modulus of the field and its variance as the criterion of interference (§4), the
    figure-8 recalibration: :mod:`pdr_mag.calibration.sphere`, :mod:`~pdr_mag.calibration.gravity`,
    :mod:`~pdr_mag.calibration.online`, :mod:`pdr_mag.fusion.detectors`.
[Huang2018]
    Huang Jingli, Zhang Xiangyu, Dai Hongde, Wang Xibin, Li Fei, Qi Yahui, Meng Lei (Naval Aviation
    University of the PLA): *Off-line correction method of three-axis magnetometer based on noise
    compensation*.  Chinese invention patent application, 2018.  (黄婧丽 等, 中国人民解放军海军航空大学.
    基于噪声补偿的三轴磁强计线下校正方法.)  The noise-compensated (adjusted) least squares with an unknown
    noise level (steps 1–2) and the ellipsoid-constrained fit (step 3): :mod:`pdr_mag.calibration.ellipsoid`.

Methods from elsewhere (Li & Griffiths 2004, Kukush et al., Alonso & Shuster) are named where they are used.
"""
