/* HBVM's state in REBOUND and its step's context block, as named C structs.
 *
 * This file is the one table of both layouts.  The C glue (glue.c) reads the members by name;
 * hbvm_md/rebound/layout.py reads this file (the members' names, types and order: one member a
 * line, every member 8 bytes, so that a member's offset is 8 times its position) and gives the
 * Python host and the numba step their slot numbers from it (SL_<MEMBER> for the state,
 * <MEMBER> upper-cased for the context block); the glue exports offsetof() of every member and
 * hbvm_md.rebound.cglue checks the two agree.  A member added, moved or renamed here moves
 * every reader at once.  Saved members are described to REBOUND (its binary format, by name,
 * so a member added here leaves older files readable: a field they lack keeps the value
 * ``create`` gave it) by layout.SAVED, at their offsetof.
 *
 * Members are one of: int64_t, double, a pointer (double *, void *, hbvm_rb_fn); an array is
 * `TYPE name[N];` with N a literal. */
#ifndef HBVM_STATE_H
#define HBVM_STATE_H

#include <stdint.h>

/* the host's callbacks and the steps: int (*)(struct reb_simulation *, void *) */
typedef int (*hbvm_rb_fn)(void *r, void *p);

/* r->integrator.state: created by the host's `create` (hbvm_md.rebound.host._create), freed
 * by glue.c's release */
struct hbvm_rb_state {
    /* saved: the settings, the method among them */
    int64_t s;
    int64_t k;
    int64_t nodes;
    int64_t max_iter;
    int64_t adaptive;
    double epsilon;
    double min_dt;
    double tol;
    double etol;                  /* saved as energy_tol */
    /* saved: the previous step, the energies (the step's eref: integrators.core.N_EREF) */
    double h_prev;
    double eref;
    double alpha;
    double slope;
    double eref_run;
    double tmean_run;
    double time_run;
    double tmax_run;
    int64_t method;
    int64_t nsteps;
    int64_t rejected;
    int64_t resyncs;
    /* saved: arrays REBOUND allocates, saves and restores (their counts beside them) */
    double *y;                    /* saved as state: the double-double state (y, cy) */
    int64_t ny;
    double *gamma;
    int64_t ngamma;
    double *counters;
    int64_t ncounters;
    /* not saved: this process's addresses, and what a failed step recorded */
    hbvm_rb_fn core;              /* the step for this state's context (0: prepare first) */
    int64_t ctx;                  /* the context block (struct hbvm_rb_context) */
    hbvm_rb_fn prepare;
    hbvm_rb_fn fail;
    void *free;                   /* the C library's free */
    int64_t echeck;               /* 1: the energy check runs, -1: nothing to check */
    int64_t status;
    double h_fail;
    double t_fail;
    double cause_err;
    double cause_status;
    double res[5];                /* loop.attempt's res (N_RES) */
    /* saved (added later: after the unsaved members so that nothing above moved) */
    double max_dt;
    int64_t kepler;
    double t_comp;
    double t_written;
    double run_err;               /* saved as error_estimate */
    double eref_masses;
    int64_t run_warned;           /* not saved */
    int64_t control;              /* saved as controller */
    hbvm_rb_fn forget;            /* not saved: the host drops its record of this state
                                   * (release calls it first; 0 once Python is finishing) */
};

/* the step's context block: this header (addresses of the arrays that follow it, their sizes,
 * REBOUND's offsets in 8-byte words for the numba step), built by host._context */
struct hbvm_rb_context {
    /* the arrays' addresses */
    int64_t a_yt;
    int64_t a_cyt;
    int64_t a_gammat;
    int64_t a_ereft;
    int64_t a_written;
    int64_t a_minv;
    int64_t a_kinw;
    int64_t a_params;
    int64_t a_tn;
    int64_t a_ts;
    int64_t a_wp;
    int64_t a_cp;
    int64_t a_nv;
    int64_t a_nvinv;
    int64_t a_nm;
    int64_t a_work;
    int64_t a_cwork;
    int64_t a_clock;
    int64_t a_e1;
    int64_t a_et;
    int64_t a_ew;
    int64_t a_ebuf;
    int64_t a_ezero;
    int64_t a_host;
    /* sizes */
    int64_t d_s;
    int64_t d_k;
    int64_t d_nodes;
    int64_t d_m;
    int64_t d_n;
    int64_t d_p;
    int64_t d_nf;
    int64_t d_nc;
    int64_t d_ptr;
    int64_t d_method;
    /* the shapes of the method's packed arrays: tn (2, tnc), ts (tsr, s), Wp (wpp, s, kk),
     * Cp (cpp, kk, s) */
    int64_t d_tnc;
    int64_t d_tsr;
    int64_t d_wpp;
    int64_t d_cpp;
    int64_t d_kk;
    /* REBOUND's offsets in doubles (the numba step's; the C glue reads rebound.h) */
    int64_t r_t;
    int64_t r_g;
    int64_t r_dt;
    int64_t r_dtl;
    int64_t r_n;
    int64_t r_particles;
    int64_t r_nactive;
    int64_t r_head;
    int64_t r_stride;
    int64_t r_x;
    int64_t r_vx;
    int64_t r_m;
    /* the words of reb_simulation holding the settings HBVM checks (layout.CONFIG_FIELDS),
     * and their values when the step was prepared */
    int64_t c_words[8];
    int64_t c_values[8];
    /* the variational part */
    int64_t a_v;
    int64_t a_vt;
    int64_t a_dg;
    int64_t a_dgt;
    int64_t a_dgs;
    int64_t a_tw;
    int64_t a_tcw;
    int64_t a_tcount;
    int64_t a_vidx;
    int64_t d_nv;
    int64_t d_tgf;
    int64_t d_tgc;
    int64_t d_pvar;
    int64_t d_megno_fn;
    int64_t r_pvar;
    int64_t r_megno_on;
    int64_t r_megno_t0;
    /* 1: the step runs on REBOUND's own accelerations (hbvm_md.rebound.forces) */
    int64_t d_host;
    int64_t a_tp;
    int64_t a_to;
    int64_t d_kepler;             /* 1: the composed step's context */
    int64_t r_status;             /* REBOUND's status (its offset in bytes) */
    int64_t d_follow;             /* 1: test particles solved after the sources (the C step:
                                   * the followers block at params[d_m + 3]) */
};

#endif
